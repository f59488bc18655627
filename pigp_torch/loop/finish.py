r"""The end of a run of :func:`pigp_torch.loop.optimize`: the restore (initial knobs, or the best
point after a control reading and its confirmation), the end record, and the result or the error.

Restore rules: after a failure the initial knobs are set back (unless ``restore="none"``); after a
completed run ``restore`` decides (``"initial"``, ``"best"``: a control reading at the first
evaluation's point, then the best point confirmed by fresh readings that read no worse than the
control reading, else the initial knobs; ``"none"``). The knobs are then read back (readbacks
and setpoints) for the end record.
"""

from __future__ import annotations

import contextlib
import dataclasses
import warnings

import pandas as pd
import torch

from pigp_torch._utils import DTYPE
from pigp_torch._utils import utc_now as _utc_now
from pigp_torch.loop.moves import SETPOINT_TOL, setpoints_of
from pigp_torch.loop.readings import CONTROL_READS, below_start, check_readings, confirm_best
from pigp_torch.loop.session import Run
from pigp_torch.loop.signals import classify
from pigp_torch.loop.steps import best_row


@dataclasses.dataclass(eq=False)
class Ending:
    """How a run ended: its status and reason, the restore's outcome and the best row."""

    error: BaseException | None
    status: str
    reason: str
    best: dict | None
    restored_to: str = "none"
    final_knobs: object = None
    final_setpoints: object = None
    restore_error: BaseException | None = None
    restored: bool = True
    attempts_made: int = 0
    attempt_errors: list = dataclasses.field(default_factory=list)
    target: torch.Tensor | None = None
    confirmation: dict | None = None
    control: dict | None = None
    rejected_best: dict | None = None


def _control_reading(run: Run, rows: list[dict], out: Ending, reference) -> str | None:
    """Restore to the first evaluation's point and read it again (the control); returns why the
    best point is not to be trusted (the machine or its instrument changed), or ``None``."""
    first = rows[0]
    # control: the first evaluation's point, its logged value known; usually the initial
    # setpoints, where a rejected best ends anyway
    out.target = torch.tensor([first[n] for n in run.names], dtype=DTYPE)
    ref = reference if torch.equal(out.target, run.x_initial) else None
    out.restore_error, out.attempts_made, out.attempt_errors = run.restore_to(
        out.target, "restore control", ref
    )
    if out.restore_error is not None:
        return None
    out.control = check_readings(
        run.fresh(out.target, first["step"], "control reading"), first["y"], run.judge,
        CONTROL_READS, selection=False,
    )  # fmt: skip
    if out.control.get("abandoned"):
        out.restore_error = KeyboardInterrupt(out.control["message"])
    elif not out.control["confirmed"]:
        return (
            "the machine or its instrument changed during the run: a control "
            f"reading at evaluation {first['step'] + 1}'s setting: "
            f"{out.control['message']}"
        )
    return None


def _restore_best(run: Run, rows: list[dict], out: Ending, reference) -> None:
    """``restore="best"``: the control reading, the best point and its confirmation; the initial
    knobs when either fails (unless a second signal stops the restore)."""
    best = out.best
    why, where = None, "the best point"
    if rows[0]["step"] != best["step"]:
        where = "the first evaluation's point (control)"
        why = _control_reading(run, rows, out, reference)
    if out.restore_error is None and why is None:
        out.target, where = torch.tensor(best["x"], dtype=DTYPE), "the best point"
        out.restore_error, more, errs = run.restore_to(out.target, "restore best", None)
        out.attempts_made, out.attempt_errors = out.attempts_made + more, out.attempt_errors + errs
        if out.restore_error is None:
            out.confirmation = confirm_best(
                run.fresh(out.target, best["step"], "confirming the best point"),
                best["y"], run.judge, run.maximize,
            )  # fmt: skip
            if out.confirmation.get("abandoned"):  # a second signal: stop here
                out.restore_error = KeyboardInterrupt(out.confirmation["message"])
            elif not out.confirmation["confirmed"]:
                why = f"the best point did not reproduce: {out.confirmation['message']}"
            else:  # it reproduced: never left at a point that reads worse than the start
                worse = below_start(out.confirmation, out.control, run.maximize)
                if worse is not None:
                    out.confirmation["confirmed"] = False
                    why = f"the best point reads worse than the start: {worse}"
    if out.restore_error is None and why is None:
        out.restored_to = "best (confirmed)"
    elif not isinstance(out.restore_error, KeyboardInterrupt):
        if why is None:
            why = f"the knobs could not be set to {where}: {out.restore_error}"
        # stack: here, _restore, end_run, optimize, optimize's caller
        warnings.warn(f"{why}; restoring the initial knobs instead", stacklevel=5)
        if run.log is not None:
            message = f"{why}; restoring the initial knobs instead"
            with contextlib.suppress(Exception):
                run.log.write("notice", step=best["step"], time=_utc_now(), message=message)
        out.target = run.x_initial
        out.restore_error, more, errs = run.restore_to(out.target, "restore initial", reference)
        out.attempts_made, out.attempt_errors = out.attempts_made + more, out.attempt_errors + errs
        out.restored_to = "initial (best not confirmed)"
        out.rejected_best, out.best = best, None
    else:
        out.restored_to = "best"


def _restore_goal(run: Run, out: Ending, goal, reference) -> None:
    """A track run's end: the knobs to ``goal``, ``(name, x)`` (``x`` ``None``: left where they
    are); when they cannot be set there (not a second signal), to the initial knobs instead."""
    out.restored_to, out.target = goal
    if out.target is None:
        return
    out.restore_error, out.attempts_made, out.attempt_errors = run.restore_to(
        out.target, f"restore {out.restored_to}", None
    )
    if out.restore_error is None or isinstance(out.restore_error, KeyboardInterrupt):
        return
    # stack: here, _restore, end_run, track, track's caller
    warnings.warn(f"the knobs could not be set to the {goal[0]}: {out.restore_error}; "
                  "restoring the initial knobs instead", stacklevel=5)  # fmt: skip
    out.target, out.restored_to = run.x_initial, f"initial ({goal[0]} not reached)"
    out.restore_error, more, errs = run.restore_to(out.target, "restore initial", reference)
    out.attempts_made, out.attempt_errors = out.attempts_made + more, out.attempt_errors + errs


def _restore(run: Run, rows: list[dict], out: Ending, goal=None) -> None:
    """Put the knobs where the restore rules say (or at ``goal``, ``(name, x or None)``: a
    track run's end chosen by its caller; ``None``: left where they are), then read where they
    are."""
    opts, objective = run.opts, run.objective
    # initial knobs after any failure; initial / best / none after a completed run
    mode = opts.restore if out.error is None else ("none" if opts.restore == "none" else "initial")
    if mode == "best" and out.best is None:
        mode = "initial"
    # a knob whose readback was off its setpoint at the start may read off it again
    reference = run.rb_found if torch.equal(run.x_initial, run.x_found) else None
    if goal is not None:
        _restore_goal(run, out, goal, reference)
    elif mode == "best":
        _restore_best(run, rows, out, reference)
    elif mode == "initial":
        out.target = run.x_initial
        out.restore_error, out.attempts_made, out.attempt_errors = run.restore_to(
            out.target, "restore initial", reference
        )
        out.restored_to = "initial"
    out.restored = out.restore_error is None
    if not out.restored:
        out.restored_to = f"{out.restored_to} (failed)"
    try:
        out.final_knobs = torch.as_tensor(objective.get(), dtype=DTYPE).reshape(-1).tolist()
    except Exception as err:  # the readback itself failed: say so in the log
        out.final_knobs = f"unavailable: {type(err).__name__}: {err}"
    try:
        out.final_setpoints = setpoints_of(objective).tolist()
    except Exception as err:
        out.final_setpoints = f"unavailable: {type(err).__name__}: {err}"


def _knobs_against_target(run: Run, out: Ending) -> dict:
    """``{"knobs_at_target": [...], "knobs_not_at_target": [...]}``: a knob is at the restore
    target when its setpoint read at the end equals it (within ``SETPOINT_TOL`` of the range) and
    its readback is within ``readback_tol`` of the range of it (or of the readback found at the
    start, for a target that is the setpoints found); ``{}`` when they could not be read."""
    sp, rb = out.final_setpoints, out.final_knobs
    if not isinstance(sp, list) or not isinstance(rb, list):
        return {}
    width = run.bounds[1] - run.bounds[0]
    target = out.target
    sp, rb = torch.tensor(sp, dtype=DTYPE), torch.tensor(rb, dtype=DTYPE)
    at = (sp - target).abs() <= SETPOINT_TOL * width
    near = (rb - target).abs() <= run.opts.readback_tol * width
    if run.rb_found is not None and torch.equal(target, run.x_found):
        near |= (rb - run.rb_found).abs() <= run.opts.readback_tol * width
    ok = (at & near).tolist()
    return {
        "knobs_at_target": [n for n, k in zip(run.names, ok, strict=True) if k],
        "knobs_not_at_target": [n for n, k in zip(run.names, ok, strict=True) if not k],
    }


def _write_end(run: Run, rows: list[dict], out: Ending, guard) -> None:
    """The end record (a failure to write it is raised only when nothing else failed, and
    warned of only when no earlier write failed: that failure is reported already)."""
    known = run.log.write_error if run.log is not None else None
    try:
        end = {"restored_to": out.restored_to, "final_knobs": out.final_knobs}
        n = rows[-1]["step"] + 1 if rows else 0  # rows may be the last ones only (a track run)
        end.update(n_evaluations=n, best=out.best)
        if run.is_machine:
            end.update(restored=out.restored, last_setpoint=run.last_acknowledged())
            end.update(last_intended=run.sent["last"], final_setpoints=out.final_setpoints)
            end.update(restore_attempts=out.attempts_made)
            if out.target is not None:
                end["restore_target"] = out.target.tolist()
                end.update(_knobs_against_target(run, out))
            for key, value in (("control_reading", out.control),
                               ("best_confirmation", out.confirmation),
                               ("rejected_best", out.rejected_best)):  # fmt: skip
                if value is not None:
                    end[key] = value
            if out.attempt_errors:
                end["restore_errors"] = out.attempt_errors
        if guard.deferred:
            end["deferred_signals"] = list(guard.deferred)
        if out.error is not None and out.restore_error is not None:
            end["restore_error"] = f"{type(out.restore_error).__name__}: {out.restore_error}"
        run.log.log_end(out.status, out.reason, **end)
    except Exception as err:
        if out.error is None and out.restore_error is None:
            raise
        if known is None:  # stack: here, end_run, optimize, optimize's caller
            warnings.warn(f"could not write the end record to the run log: {err!r}", stacklevel=4)
    finally:
        if run.own_log:
            run.log.close()


def end_run(
    run: Run, rows: list[dict], error, status: str, reason: str, guard, goal=None
) -> Ending:
    """The restore and the end record (signals deferred by the caller); ``goal``: see
    :func:`_restore`."""
    out = Ending(error, status, reason, best_row(rows, run.names, run.maximize))
    if run.is_machine:
        _restore(run, rows, out, goal)
    if error is None and out.restore_error is not None:
        out.status, out.reason = classify(out.restore_error)
        out.reason = f"restoring the knobs failed: {out.reason}"
    if run.log is not None:
        _write_end(run, rows, out, guard)
    return out


def result(run: Run, rows: list[dict], out: Ending, guard) -> pd.DataFrame:
    """The run's table, or its error raised (the original error before a failed restore's)."""
    if out.error is not None:
        if out.restore_error is not None:
            warnings.warn(
                f"could not restore the initial knobs after a failure ({out.attempts_made} "
                f"attempt(s)): {out.restore_error!r}; last setpoint acknowledged: "
                f"{run.last_acknowledged()}",
                stacklevel=3,
            )
        raise out.error
    if out.restore_error is not None:
        raise out.restore_error
    if guard.deferred:
        warnings.warn(
            f"signal(s) {guard.deferred} arrived while the knobs were restored after a completed "
            "run; they were ignored",
            stacklevel=3,
        )
    names = run.names
    table = pd.DataFrame(rows, columns=["step", *names, "y", "method", "ask_time_s", "eval_time_s"])
    return table.astype({"step": "int64", **dict.fromkeys(names, "float64"), "y": "float64"})
