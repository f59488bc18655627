r"""Track mode: keep a machine tuned for a shift (:func:`track`).

A one-shot run (:func:`~pigp_torch.loop.optimize`) spends a budget and puts the knobs back; a
track run keeps asking the optimizer, evaluation after evaluation, until it is stopped (Ctrl-C,
SIGTERM, SIGHUP), its wall-clock limit ``time_limit_s`` passes or ``max_readings`` evaluations
are made (a bound in count, so the loop is bounded in time *and* count), whichever comes first.
Every safety rule of the one-shot path holds unchanged (the same start, steps and end:
checked ramps within ``max_step``, intent records, the hash-chained log, plausible-reading
checks, alarm severity, the noise measured at the start, the objective floor).

**Bounded memory.** A shift is long: the loop keeps the last ``keep`` evaluations in memory
(default :data:`KEEP_ROWS`; the returned table and the end record's ``best`` are of those; the
run log holds every one), and the plausible-reading rule compares a reading with the median of
the last ``keep`` accepted readings (on a drifting machine the level moves; a one-shot run uses
all of its readings), so a run of any length holds the same memory and file descriptors (the
optimizer's own history is the optimizer's: a tracker forgets).

Each evaluation record also carries ``tracked``: the optimizer's tracked unknowns
(:meth:`~pigp_torch.optimizers.base.AskTellOptimizer.tracked`, ``{name: [value, unit]}``, the
estimate the setting was asked with), beside its wall-clock times ``t_set`` / ``t_read`` (s
since the epoch).

**Where the knobs are left** (``end_at``), at the time limit, the count limit *or a stop by a
signal* (the usual end of a shift):

* ``"estimate"`` (default): :meth:`~pigp_torch.optimizers.base.AskTellOptimizer.recommend`, the
  optimizer's current estimate of the optimum (for a model-free optimizer its best reading);
  an estimate that is not finite or lies outside the bounds is not used: the initial knobs are
  set back instead (a warning and a ``notice`` record say so);
* ``"best"``: the best of the last ``recent`` readings (default 20). On a drifting machine a
  best reading from hours ago is stale: its setting no longer gives its value. It is set
  without the one-shot's control reading and confirmation (the machine is expected to have
  changed since the first evaluation, which that control compares against);
* ``"current"``: left where the last evaluation put them;
* ``"initial"``: the knobs found at the start (of the first session, on a resume).

When the knobs cannot be set to the estimate or the recent best (the machine refuses it through
the restore window), the initial knobs are set back instead (a warning; ``restored_to``:
``"initial (estimate not reached)"``).

After any other end (a machine error, a refused setting, the objective floor, a full log disk,
a bug) the initial knobs are set back, as in a one-shot run. A second signal while the end
target is computed or reached abandons the restore (the knobs are left, and the end record says
where they are).

**Resume.** A track run resumes like a one-shot run (:func:`~pigp_torch.data.runlog.replay`;
``max_readings`` counts the logged evaluations too); its time limit counts from the resume.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import time
import warnings
from collections import deque
from collections.abc import Callable

import pandas as pd
import torch

from pigp_torch._utils import DTYPE
from pigp_torch._utils import utc_now as _utc_now
from pigp_torch.loop.finish import end_run, result
from pigp_torch.loop.options import RunOptions
from pigp_torch.loop.session import Run, open_log, run_all_steps, start_run
from pigp_torch.loop.signals import SignalGuard, classify

#: Where a track run may leave the knobs (``end_at``).
TRACK_ENDS = ("estimate", "best", "current", "initial")
#: Default number of recent readings among which ``end_at="best"`` picks.
RECENT_READINGS = 20
#: Default number of evaluations a track run keeps in memory (its table).
KEEP_ROWS = 1000


def tracked_record(optimizer) -> dict:
    """``{"tracked": {name: [value, unit]}}`` of an optimizer's tracked unknowns (JSON)."""
    return {"tracked": {str(k): [float(v), str(u)] for k, (v, u) in optimizer.tracked().items()}}


def _estimate(run: Run, optimizer) -> tuple[torch.Tensor | None, str]:
    """``(x, "")``: the optimizer's recommendation checked (``d``, finite, inside the bounds);
    ``(None, why)`` when it cannot be used."""
    try:
        x = torch.as_tensor(optimizer.recommend(), dtype=DTYPE).reshape(-1).clone()
    except Exception as err:
        return None, f"the optimizer gave no estimate ({type(err).__name__}: {err})"
    if x.numel() != len(run.names) or not torch.isfinite(x).all():
        return None, f"the estimate {x.tolist()} is not {len(run.names)} finite values"
    if run.bounds is not None and ((x < run.bounds[0]) | (x > run.bounds[1])).any():
        return None, f"the estimate {x.tolist()} lies outside the knob bounds"
    return x, ""


def _recent_best(run: Run, rows: list[dict], recent: int) -> torch.Tensor | None:
    """The setting of the best of the last ``recent`` readings (``None`` without readings)."""
    window = list(rows)[-recent:]
    if not window:
        return None
    ys = torch.tensor([r["y"] for r in window], dtype=DTYPE)
    best = window[int(ys.argmax() if run.maximize else ys.argmin())]
    return torch.tensor([best[n] for n in run.names], dtype=DTYPE)


def end_goal(run: Run, optimizer, rows: list[dict], end_at: str, recent: int):
    """Where a track run that ended normally (or by one signal) leaves the knobs:
    ``(name, x)`` for :func:`~pigp_torch.loop.finish.end_run` (``x`` ``None``: not moved), or
    ``None``: the initial knobs (``end_at="initial"``, or an estimate that cannot be used)."""
    if end_at == "current":
        return "current", None
    if end_at == "best":
        x = _recent_best(run, rows, recent)
        return None if x is None else (f"best of the last {min(recent, len(rows))} readings", x)
    if end_at == "estimate" and rows:
        x, why = _estimate(run, optimizer)
        if x is not None:
            return "estimate", x
        message = f"{why}; restoring the initial knobs instead"
        warnings.warn(message, stacklevel=3)
        if run.log is not None:
            with contextlib.suppress(Exception):
                run.log.write("notice", step=rows[-1]["step"], time=_utc_now(), message=message)
    return None


def _check(max_readings, time_limit_s, end_at: str, recent, keep) -> None:
    if int(max_readings) != max_readings or max_readings < 1:
        raise ValueError(f"max_readings must be a positive integer, got {max_readings}")
    if not (0.0 < float(time_limit_s) < math.inf):
        raise ValueError(f"time_limit_s must be positive and finite, got {time_limit_s}")
    if end_at not in TRACK_ENDS:
        raise ValueError(f"end_at must be one of {TRACK_ENDS}, got {end_at!r}")
    if int(recent) != recent or recent < 1:
        raise ValueError(f"recent must be a positive integer, got {recent}")
    if int(keep) != keep or keep < recent:
        raise ValueError(f"keep must be an integer >= recent ({recent}), got {keep}")


def track(
    objective,
    optimizer,
    max_readings: int,
    x0=None,
    *,
    time_limit_s: float,
    end_at: str = "estimate",
    recent: int = RECENT_READINGS,
    keep: int = KEEP_ROWS,
    knob_names=None,
    method: str | None = None,
    progress: bool = False,
    callback: Callable[[dict], None] | None = None,
    log=None,
    resume=None,
    options: RunOptions | None = None,
    clock: Callable[[], float] = time.monotonic,
) -> pd.DataFrame:
    r"""Keep ``objective`` tuned with ``optimizer`` until stopped, ``time_limit_s`` seconds
    (``clock``) pass or ``max_readings`` evaluations are made (see the module docstring).

    Args:
        objective: a ``Machine`` or a callable ``x (d) -> float`` (never moved or restored).
        optimizer: an :class:`~pigp_torch.optimizers.base.AskTellOptimizer` (``recommend()``).
        max_readings: the most evaluations (>= 1; a resume counts the logged ones).
        x0: ``d`` start point (``None``: a machine's knobs found; required for a callable).
        time_limit_s: the wall-clock limit, seconds from this call (> 0).
        end_at: ``"estimate"`` (default), ``"best"``, ``"current"`` or ``"initial"``.
        recent: the readings among which ``end_at="best"`` picks (default 20).
        keep: evaluations kept in memory (>= ``recent``; default :data:`KEEP_ROWS`).
        knob_names, method, progress, callback, log, resume: as
            :func:`~pigp_torch.loop.optimize`.
        options: the safety options (:class:`~pigp_torch.loop.RunOptions`; its ``restore``
            applies after a failure only and must be ``"initial"`` or ``"none"``).
        clock: seconds, monotonic (default :func:`time.monotonic`; tests pass their own).

    Returns:
        the evaluation table of :func:`~pigp_torch.loop.optimize`, its last ``keep`` rows.

    Raises:
        as :func:`~pigp_torch.loop.optimize`; ``KeyboardInterrupt`` / ``Terminated`` after a
        stop by a signal (re-raised once the knobs are at ``end_at``'s target).
    """
    _check(max_readings, time_limit_s, end_at, recent, keep)
    opts = RunOptions() if options is None else options
    if opts.restore == "best":
        raise ValueError("a track run's restore after a failure is initial or none, not best")
    if end_at == "initial":  # then the one-shot rule does it
        opts = dataclasses.replace(opts, restore="initial")
    run = start_run(objective, optimizer, x0, int(max_readings), knob_names=knob_names,
                    method=method, resume=resume, opts=opts)  # fmt: skip
    run.judge.readings = deque(run.judge.readings, maxlen=int(keep))  # the recent level
    open_log(run, log, resume)
    deadline = clock() + float(time_limit_s)
    rows: deque[dict] = deque(maxlen=int(keep))
    with SignalGuard(opts.handle_signals) as guard:
        error, status, reason, goal = None, "completed", "", None
        try:
            run_all_steps(run, optimizer, rows, progress=progress, callback=callback, guard=guard,
                          stop=lambda: clock() >= deadline,
                          record=lambda: tracked_record(optimizer))  # fmt: skip
            n = rows[-1]["step"] + 1 if rows else 0
            reason = (
                f"the time limit of {float(time_limit_s):g} s passed after {n} readings"
                if n < max_readings
                else f"max_readings ({int(max_readings)}) made"
            )
        except BaseException as err:
            error = err
            status, reason = classify(err)
        finally:
            guard.deferring = True  # from here on: restore and end record, signals deferred
        if run.is_machine and (error is None or isinstance(error, KeyboardInterrupt)):
            try:
                goal = end_goal(run, optimizer, rows, end_at, recent)
            except KeyboardInterrupt:  # a second signal: leave the knobs where they are
                goal = ("current (restore abandoned)", None)
        ending = end_run(run, list(rows), error, status, reason, guard, goal=goal)
    return result(run, list(rows), ending, guard)
