r"""The loop itself: :func:`optimize` (start point, then ask -> evaluate -> tell until the budget,
then the restore and the end record).

On a :class:`~pigp_torch.machine.base.Machine` (``set`` then ``read``) the safety rules of
:mod:`pigp_torch.loop` apply: checked settings, ramps within the step limit, bounded read retries,
readings checked against the machine's state, the objective floor, intent records, and the restore
of the initial knobs (found at the start with ``get()``; on a resume, those of the logged run's
first start):

* ``restore="initial"`` (default, the safe choice): the initial knobs are set back;
* ``restore="best"``: the best *observed* point is set (the loop's records, in the optimizer's
  direction ``optimizer.maximize``);
* ``restore="none"``: the knobs are left where they are.

If an exception escapes (including ``KeyboardInterrupt`` and SIGTERM) the initial knobs are set
back (unless ``restore="none"``) and the exception is re-raised; a failure of that restore is
reported as a warning so that it does not hide the original error. A plain callable
``objective(x) -> float`` is never moved or restored (its non-finite values are retried too).

The parts: the run's start, log and steps in :mod:`~pigp_torch.loop.session`, its end (restore,
best-point confirmation, end record) in :mod:`~pigp_torch.loop.finish`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path

import pandas as pd

from pigp_torch.data.runlog import RunLog, RunRecords
from pigp_torch.loop.finish import end_run, result
from pigp_torch.loop.options import RunOptions
from pigp_torch.loop.session import open_log, run_all_steps, start_run
from pigp_torch.loop.signals import SignalGuard, classify


def optimize(
    objective,
    optimizer,
    x0=None,
    budget: int = 100,
    *,
    knob_names=None,
    method: str | None = None,
    progress: bool = False,
    callback: Callable[[dict], None] | None = None,
    log: RunLog | str | Path | None = None,
    resume: RunRecords | list[dict] | None = None,
    options: RunOptions | None = None,
    **safety,
) -> pd.DataFrame:
    r"""Run an ask/tell optimizer on a machine or a function for ``budget`` evaluations.

    Step 0 evaluates ``x0`` and tells it (the first tell defines the optimizer's start); steps
    ``1 .. budget-1`` each ask, evaluate and tell. The budget counts every evaluation, ``x0``
    included (and, on a resume, the logged ones).

    On a :class:`~pigp_torch.machine.base.Machine` (``set`` then ``read``) the safety rules of
    :mod:`pigp_torch.loop` apply and the knobs are restored at the end (see the module docstring);
    an exception that escapes (including ``KeyboardInterrupt`` and SIGTERM) is re-raised after
    the restore. A plain callable ``objective(x) -> float`` is never moved or restored.

    Args:
        objective: a ``Machine`` or a callable ``x (d) -> float``.
        optimizer: an ask/tell optimizer (:class:`~pigp_torch.optimizers.base.AskTellOptimizer`).
        x0: ``d`` start point; ``None`` uses the machine's current knobs (must be ``None`` when
            resuming: the start point is in the log).
        budget: total number of evaluations (>= 1).
        knob_names: column names for the knobs (default: the machine's, else ``x0..x{d-1}``).
        method: value of the ``method`` column (default ``optimizer.name``).
        progress: show a tqdm progress bar.
        callback: called with each new row (a dict) after its step (not for replayed rows).
        log: a :class:`~pigp_torch.data.runlog.RunLog` (left open), or a path: a new log is created
            (or, when resuming, the log is continued) and closed at the end.
        resume: the records of a logged run (:func:`~pigp_torch.data.runlog.read_log`) or its
            evaluation records; ``optimizer`` must be fresh and built as in that run.
        options: the safety options (:class:`~pigp_torch.loop.options.RunOptions`; default
            ``RunOptions()``).
        **safety: :class:`~pigp_torch.loop.options.RunOptions` fields, over ``options``
            (``restore="best"``, ``max_step=0.1``, ...).

    Returns:
        a DataFrame with one row per evaluation and columns ``step`` (0..budget-1), one float64
        column per knob, ``y`` (observed objective), ``method``, ``ask_time_s`` (optimizer time for
        the ask and tell of that step) and ``eval_time_s`` (move and read).

    Raises:
        ValueError: bad arguments, a refused setting, or nothing left to resume.
        ReadError: no valid reading after the retries.
        RunAborted: a reading below ``objective_floor``.
        MachineError: from the machine, a reading taken while the knobs moved, or a failed
            readback check after the restore (the end record then has ``restored`` false).
        pigp_torch.data.runlog.ReplayError: the resumed log does not match the optimizer.
    """
    if int(budget) != budget or budget < 1:
        raise ValueError(f"budget must be a positive integer, got {budget}")
    opts = RunOptions(**safety) if options is None else dataclasses.replace(options, **safety)
    run = start_run(objective, optimizer, x0, int(budget), knob_names=knob_names, method=method,
                    resume=resume, opts=opts)  # fmt: skip
    open_log(run, log, resume)
    rows: list[dict] = []
    with SignalGuard(opts.handle_signals) as guard:
        error, status, reason = None, "completed", ""
        try:
            run_all_steps(run, optimizer, rows, progress=progress, callback=callback, guard=guard)
        except BaseException as err:
            error = err
            status, reason = classify(err)
        finally:
            guard.deferring = True  # from here on: restore and end record, signals deferred
        ending = end_run(run, rows, error, status, reason, guard)
    return result(run, rows, ending, guard)
