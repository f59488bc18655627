r"""The loop itself: :func:`optimize` (start point, then ask -> evaluate -> tell until the budget,
then the restore and the end record)."""

from __future__ import annotations

import contextlib
import dataclasses
import warnings
from collections.abc import Callable
from pathlib import Path

import pandas as pd
import torch

from pigp_torch._utils import DTYPE, as_knob_tensor, check_bounds
from pigp_torch._utils import utc_now as _utc_now
from pigp_torch.data.runlog import RunLog, RunRecords, evaluation_rows, replay
from pigp_torch.loop.moves import (
    averaged_parts,
    checked_read,
    effective_max_step,
    move,
    read,
    restore_knobs,
    setpoints_of,
)
from pigp_torch.loop.options import RunOptions
from pigp_torch.loop.readings import CONTROL_READS, ReadingJudge, check_readings, confirm_best
from pigp_torch.loop.signals import SignalGuard, classify
from pigp_torch.loop.steps import best_row, knob_columns, logged_initial_knobs, run_steps
from pigp_torch.machine.base import Machine, check_setting


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
    :mod:`pigp_torch.loop` apply: checked settings, ramps within the step limit, bounded read
    retries, readings checked against the machine's state, the objective floor, intent records,
    and the restore of the initial knobs (found at the start with ``get()``; on a resume, those
    of the logged run's first start):

    * ``restore="initial"`` (default, the safe choice): the initial knobs are set back;
    * ``restore="best"``: the best *observed* point is set (the loop's records, in the optimizer's
      direction ``optimizer.maximize``);
    * ``restore="none"``: the knobs are left where they are.

    If an exception escapes (including ``KeyboardInterrupt`` and SIGTERM) the initial knobs are
    set back (unless ``restore="none"``) and the exception is re-raised; a failure of that restore
    is reported as a warning so that it does not hide the original error. A plain callable
    ``objective(x) -> float`` is never moved or restored (its non-finite values are retried too).

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
            (``restore="best"``, ``moves="ramp"``, ``max_step=0.1``, ...).

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
    budget = int(budget)
    opts = RunOptions(**safety) if options is None else dataclasses.replace(options, **safety)
    is_machine = isinstance(objective, Machine)
    if not is_machine and not callable(objective):
        raise ValueError("objective must be a Machine or a callable x -> float")

    logged: list[dict] = []
    if resume is not None:
        if x0 is not None:
            raise ValueError("x0 must be None when resuming: the start point is in the log")
        logged = list(resume.evaluations if isinstance(resume, RunRecords) else resume)
        if not logged:
            raise ValueError("nothing to resume: the log holds no evaluation")
        if len(logged) >= budget:
            raise ValueError(
                f"the log already holds {len(logged)} evaluations and the budget is {budget}: "
                "raise the budget to continue the run"
            )

    # the restore target: the SETPOINTS found at the start (never readbacks); the readbacks
    # found are the reference of a knob that already read off its setpoint
    x_found = setpoints_of(objective) if is_machine else None
    rb_found = (
        torch.as_tensor(objective.get(), dtype=DTYPE).reshape(-1).clone() if is_machine else None
    )
    x_initial = x_found
    logged_initial = logged_initial_knobs(resume)
    if is_machine and logged_initial is not None:
        if logged_initial.shape != x_found.shape:
            raise ValueError(
                f"the log's initial knobs have {logged_initial.numel()} values, the machine "
                f"{x_found.numel()}"
            )
        x_initial = logged_initial
    if resume is None:
        if x0 is None:
            if not is_machine:
                raise ValueError("x0 is required when the objective is a plain callable")
            x0 = x_initial
        if not isinstance(x0, torch.Tensor):  # lists/arrays straight to float64, not via float32
            x0 = torch.as_tensor(x0, dtype=DTYPE)
        d = getattr(optimizer, "dim", None) or x0.numel()
        x0 = as_knob_tensor(x0.reshape(-1), d, name="x0")[0][0]
    else:
        d = getattr(optimizer, "dim", None) or len(logged[0]["x"])
    names = knob_columns(knob_names, objective, d)
    label = method if method is not None else getattr(optimizer, "name", type(optimizer).__name__)
    maximize = bool(getattr(optimizer, "maximize", True))
    if isinstance(resume, RunRecords) and resume.knob_names and resume.knob_names != names:
        raise ValueError(f"the resumed log has knobs {resume.knob_names}, the run has {names}")

    bounds = limit = None
    if is_machine:
        bounds = check_bounds(objective.bounds)
        if bounds.shape[1] != d:
            raise ValueError(f"the machine has {bounds.shape[1]} knobs, the optimizer {d}")
        limit = effective_max_step(objective, bounds, opts.max_step)
        if x_initial is not x_found:
            try:
                check_setting(x_initial, bounds)
            except ValueError as err:
                raise ValueError(f"the logged initial knobs are not allowed: {err}") from err
        machine_tol = getattr(objective, "tolerance", None)
        if machine_tol is not None:
            read_tol = torch.as_tensor(machine_tol, dtype=DTYPE).expand(d).clone()
        else:
            read_tol = opts.readback_tol * (bounds[1] - bounds[0])
    sent = {"last": None, "acked": None, "step": None, "purpose": "evaluation"}
    objective_range = opts.objective_range
    if objective_range is None and is_machine:
        objective_range = getattr(objective, "objective_limits", None)
    judge = ReadingJudge(opts.noise, objective_range, readings=[r["y"] for r in logged])

    def on_set(x: torch.Tensor, k: int, n: int) -> None:
        if log is not None:
            try:
                log.log_intent(x, purpose=sent["purpose"], step=sent["step"], part=k, parts=n)
            except Exception as err:
                if not sent["purpose"].startswith("restore"):
                    raise  # no move of a run without its intent on disk
                # a restore goes on even when the log cannot be written (disk full)
                warnings.warn(f"could not log the restore's intent: {err!r}", stacklevel=2)
        sent["last"] = x.tolist()

    def on_ack(x: torch.Tensor) -> None:
        sent["acked"] = x.tolist()

    def last_acknowledged():
        """The setpoints the machine last confirmed (its own account where it keeps one)."""
        acked = getattr(objective, "last_acknowledged", None)
        return acked.tolist() if isinstance(acked, torch.Tensor) else sent["acked"]

    def on_discard_at(step):
        def on_discard(reason: str, y: float) -> None:
            if log is not None:
                log.write("discarded", step=step, y=y, reason=reason, time=_utc_now())

        return on_discard

    def evaluate(x: torch.Tensor, ramp: bool, step: int) -> tuple[float, int]:
        if is_machine:
            sent["step"], sent["purpose"] = step, "evaluation"
            move(objective, x, bounds, limit, ramp=ramp, on_set=on_set, on_ack=on_ack)
            on_discard = on_discard_at(step)
            if not opts.check_readings:
                return read(
                    objective.read, opts.read_retries, opts.retry_interval, judge, on_discard,
                    lambda: averaged_parts(objective),
                )  # fmt: skip
            return checked_read(
                objective, x, read_tol, opts.read_retries, opts.retry_interval, on_discard, judge
            )
        return read(
            lambda: objective(x), opts.read_retries, opts.retry_interval, judge, on_discard_at(step)
        )

    own_log = log is not None and not isinstance(log, RunLog)
    if own_log:
        if resume is not None:
            log = RunLog.append(log)
        else:
            header = {"knob_names": names, "method": label, "budget": budget}
            if bounds is not None:
                header["bounds"] = bounds.tolist()
            log = RunLog.create(log, header)
    if log is not None and log.header.get("knob_names") not in (None, names):
        if own_log:
            log.close()
        raise ValueError(f"the run log has knobs {log.header['knob_names']}, the run has {names}")

    rows: list[dict] = []
    with SignalGuard(opts.handle_signals) as guard:
        error, status, reason = None, "completed", ""
        try:
            if logged:
                replay(optimizer, logged, progress=progress)
                rows = evaluation_rows(logged, names, label)
            run_steps(
                evaluate,
                optimizer,
                x0,
                len(rows),
                budget,
                rows,
                names=names,
                label=label,
                moves=opts.moves,
                log=log,
                x_initial=x_initial,
                x_found=x_found,
                rb_found=rb_found,
                reading_info=(lambda: getattr(objective, "last_reading", None)),
                callback=callback,
                progress=progress,
                objective_floor=opts.objective_floor,
                guard=guard,
            )
        except BaseException as err:
            error = err
            status, reason = classify(err)
        finally:
            guard.deferring = True  # from here on: restore and end record, signals deferred

        best = best_row(rows, names, maximize)
        restored_to, final_knobs, restore_error = "none", None, None
        restored, attempts_made, attempt_errors = True, 0, []
        target, confirmation, final_setpoints = None, None, None
        control, rejected_best = None, None
        if is_machine:
            # initial knobs after any failure; initial / best / none after a completed run
            mode = (
                opts.restore if error is None else ("none" if opts.restore == "none" else "initial")
            )
            if mode == "best" and best is None:
                mode = "initial"
            # a knob whose readback was off its setpoint at the start may read off it again
            reference = rb_found if torch.equal(x_initial, x_found) else None

            def restore_to(goal, purpose, ref):
                sent["purpose"], sent["step"] = purpose, None
                return restore_knobs(
                    objective,
                    goal,
                    bounds,
                    limit,
                    attempts=opts.restore_attempts,
                    interval=opts.restore_interval,
                    readback_tol=opts.readback_tol,
                    on_set=on_set,
                    on_ack=on_ack,
                    reference=ref,
                )

            if mode == "best":

                def fresh(x, step, what):
                    def discard(reason: str, y: float) -> None:
                        on_discard_at(step)(f"{what}: {reason}", y)

                    return lambda: checked_read(
                        objective, x, read_tol, opts.read_retries, opts.retry_interval, discard,
                        ReadingJudge(None, objective_range),
                    )[0]  # fmt: skip

                why, where = None, "the best point"
                first = rows[0]
                if first["step"] != best["step"]:
                    # control: the first evaluation's point, its logged value known; usually the
                    # initial setpoints, where a rejected best ends anyway
                    target = torch.tensor([first[n] for n in names], dtype=DTYPE)
                    where = "the first evaluation's point (control)"
                    ref = reference if torch.equal(target, x_initial) else None
                    restore_error, attempts_made, attempt_errors = restore_to(
                        target, "restore control", ref
                    )
                    if restore_error is None:
                        control = check_readings(
                            fresh(target, first["step"], "control reading"), first["y"], judge,
                            CONTROL_READS, selection=False,
                        )  # fmt: skip
                        if control.get("abandoned"):
                            restore_error = KeyboardInterrupt(control["message"])
                        elif not control["confirmed"]:
                            why = (
                                "the machine or its instrument changed during the run: a control "
                                f"reading at evaluation {first['step'] + 1}'s setting: "
                                f"{control['message']}"
                            )
                if restore_error is None and why is None:
                    target, where = torch.tensor(best["x"], dtype=DTYPE), "the best point"
                    restore_error, more, errs = restore_to(target, "restore best", None)
                    attempts_made, attempt_errors = attempts_made + more, attempt_errors + errs
                    if restore_error is None:
                        confirmation = confirm_best(
                            fresh(target, best["step"], "confirming the best point"),
                            best["y"], judge, maximize,
                        )  # fmt: skip
                        if confirmation.get("abandoned"):  # a second signal: stop here
                            restore_error = KeyboardInterrupt(confirmation["message"])
                        elif not confirmation["confirmed"]:
                            why = f"the best point did not reproduce: {confirmation['message']}"
                if restore_error is None and why is None:
                    restored_to = "best (confirmed)"
                elif not isinstance(restore_error, KeyboardInterrupt):
                    if why is None:
                        why = f"the knobs could not be set to {where}: {restore_error}"
                    warnings.warn(f"{why}; restoring the initial knobs instead", stacklevel=2)
                    if log is not None:
                        message = f"{why}; restoring the initial knobs instead"
                        with contextlib.suppress(Exception):
                            log.write("notice", step=best["step"], time=_utc_now(),
                                      message=message)  # fmt: skip
                    target = x_initial
                    restore_error, more, errs = restore_to(target, "restore initial", reference)
                    attempts_made, attempt_errors = attempts_made + more, attempt_errors + errs
                    restored_to = "initial (best not confirmed)"
                    rejected_best, best = best, None
                else:
                    restored_to = "best"
            elif mode == "initial":
                target = x_initial
                restore_error, attempts_made, attempt_errors = restore_to(
                    target, "restore initial", reference
                )
                restored_to = "initial"
            restored = restore_error is None
            if not restored:
                restored_to = f"{restored_to} (failed)"
            try:
                final_knobs = torch.as_tensor(objective.get(), dtype=DTYPE).reshape(-1).tolist()
            except Exception as err:  # the readback itself failed: say so in the log
                final_knobs = f"unavailable: {type(err).__name__}: {err}"
            try:
                final_setpoints = setpoints_of(objective).tolist()
            except Exception as err:
                final_setpoints = f"unavailable: {type(err).__name__}: {err}"
        if error is None and restore_error is not None:
            status, reason = classify(restore_error)
            reason = f"restoring the knobs failed: {reason}"

        if log is not None:
            try:
                end = {"restored_to": restored_to, "final_knobs": final_knobs}
                end.update(n_evaluations=len(rows), best=best)
                if is_machine:
                    end.update(restored=restored, last_setpoint=last_acknowledged())
                    end.update(last_intended=sent["last"], final_setpoints=final_setpoints)
                    end.update(restore_attempts=attempts_made)
                    if target is not None:
                        end["restore_target"] = target.tolist()
                    if control is not None:
                        end["control_reading"] = control
                    if confirmation is not None:
                        end["best_confirmation"] = confirmation
                    if rejected_best is not None:
                        end["rejected_best"] = rejected_best
                    if attempt_errors:
                        end["restore_errors"] = attempt_errors
                if guard.deferred:
                    end["deferred_signals"] = list(guard.deferred)
                if error is not None and restore_error is not None:
                    end["restore_error"] = f"{type(restore_error).__name__}: {restore_error}"
                log.log_end(status, reason, **end)
            except Exception as err:
                if error is None and restore_error is None:
                    raise
                warnings.warn(
                    f"could not write the end record to the run log: {err!r}", stacklevel=2
                )
            finally:
                if own_log:
                    log.close()

    if error is not None:
        if restore_error is not None:
            warnings.warn(
                f"could not restore the initial knobs after a failure ({attempts_made} "
                f"attempt(s)): {restore_error!r}; last setpoint acknowledged: "
                f"{last_acknowledged()}",
                stacklevel=2,
            )
        raise error
    if restore_error is not None:
        raise restore_error
    if guard.deferred:
        warnings.warn(
            f"signal(s) {guard.deferred} arrived while the knobs were restored after a completed "
            "run; they were ignored",
            stacklevel=2,
        )
    table = pd.DataFrame(rows, columns=["step", *names, "y", "method", "ask_time_s", "eval_time_s"])
    return table.astype({"step": "int64", **dict.fromkeys(names, "float64"), "y": "float64"})
