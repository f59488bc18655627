r"""At the machine boundary: checked settings and ramps within the step limit, readback checks,
bounded read retries, readings checked against the machine's state, and the restore.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

import torch

from pigp_torch._utils import DTYPE, max_step_tensor
from pigp_torch.machine.base import check_setting, ramp_steps
from pigp_torch.machine.errors import MachineError, ReadError

#: Ramp steps are planned at this fraction of the step limit: a machine that measures the step
#: from its readbacks (``EpicsMachine``) sees the readback within its tolerance of the setpoint.
RAMP_FRACTION = 0.99


def effective_max_step(machine, bounds: torch.Tensor, max_step) -> torch.Tensor | None:
    """Elementwise minimum of the machine's and the loop's step limits (absolute, ``d``)."""
    limits = [
        max_step_tensor(m, bounds)
        for m in (getattr(machine, "max_step", None), max_step)
        if m is not None
    ]
    if not limits:
        return None
    out = limits[0]
    for m in limits[1:]:
        out = torch.minimum(out, m)
    return out


def move(machine, target: torch.Tensor, bounds, limit, *, ramp: bool, on_set=None) -> int:
    r"""Send ``target`` to ``machine``: one checked ``set``, or a checked ramp; returns the sets.

    Every setting passes :func:`check_setting` (bounds; step from the previous setting sent, the
    first measured from ``machine.get()``) before ``machine.set``; ``on_set(x, k, n)`` (if given)
    is called just before the ``k``-th of ``n`` sets (the intent record).
    """
    target = check_setting(target, bounds)
    previous = torch.as_tensor(machine.get(), dtype=DTYPE).reshape(-1)
    planned = limit * RAMP_FRACTION if ramp and limit is not None else None
    steps = ramp_steps(previous, target, planned)
    for k, x in enumerate(steps, start=1):
        # intermediate points are convex combinations; the clamp only removes round-off
        x = torch.minimum(torch.maximum(x, bounds[0]), bounds[1])
        x = check_setting(x, bounds, current=previous, max_step=limit)
        if on_set is not None:
            on_set(x, k, len(steps))
        machine.set(x.clone())
        previous = x
    return len(steps)


def verify_readback(machine, target: torch.Tensor, bounds, readback_tol: float) -> torch.Tensor:
    got = torch.as_tensor(machine.get(), dtype=DTYPE).reshape(-1)
    tol = readback_tol * (bounds[1] - bounds[0])
    bad = ((got - target).abs() > tol).nonzero().flatten().tolist()
    if bad:
        raise MachineError(
            f"readback check failed on knob indices {bad}: read {got[bad].tolist()}, "
            f"expected {target[bad].tolist()} (tolerance {tol[bad].tolist()})"
        )
    return got


def read(measure: Callable[[], float], retries: int, interval: float) -> tuple[float, int]:
    """A valid (finite) reading and the number of attempts it took; ``ReadError`` after
    ``retries + 1`` invalid ones (``interval`` seconds apart)."""
    problems = []
    for attempt in range(1, retries + 2):
        if attempt > 1 and interval > 0:
            time.sleep(interval)
        try:
            y = float(measure())
        except (ReadError, TimeoutError) as err:
            problems.append(f"{type(err).__name__}: {err}")
            continue
        if math.isfinite(y):
            return y, attempt
        problems.append(f"non-finite reading {y}")
    raise ReadError(f"no valid reading in {retries + 1} attempts ({'; '.join(problems)})")


def machine_state(machine) -> dict:
    """What a reading is checked against: readbacks, setpoints and the disconnection count
    (the latter two only where the machine offers them)."""
    state = {"readback": torch.as_tensor(machine.get(), dtype=DTYPE).reshape(-1)}
    setpoints = getattr(machine, "setpoints", None)
    if callable(setpoints):
        state["setpoint"] = torch.as_tensor(setpoints(), dtype=DTYPE).reshape(-1)
    if hasattr(machine, "disconnections"):
        state["disconnections"] = int(machine.disconnections)
    return state


def off_setting(state: dict, x: torch.Tensor, tol: torch.Tensor) -> list[int]:
    return ((state["readback"] - x).abs() > tol).nonzero().flatten().tolist()


def checked_read(
    machine, x: torch.Tensor, tol: torch.Tensor, retries: int, interval: float, on_discard
) -> tuple[float, int]:
    r"""A valid reading of ``machine`` at setting ``x``, checked against the machine's state.

    Before each attempt the readbacks must be within ``tol`` of ``x`` (else ``MachineError``);
    after it, the readbacks must still be there, the setpoints unchanged and no connection lost.
    A reading that fails the after-check is reported to ``on_discard(reason, y)`` and taken
    again (within the ``retries + 1`` attempts) if the knobs are still at ``x``; otherwise
    ``MachineError``. Invalid readings are retried as in :func:`read`.

    Returns:
        ``(y, attempts)``.

    Raises:
        MachineError: the knobs are not (or no longer) at ``x``.
        ReadError: no valid, consistent reading in ``retries + 1`` attempts.
    """
    problems = []
    for attempt in range(1, retries + 2):
        if attempt > 1 and interval > 0:
            time.sleep(interval)
        before = machine_state(machine)
        off = off_setting(before, x, tol)
        if off:
            raise MachineError(
                f"knobs {off} are not at the setting before the reading: readback "
                f"{before['readback'][off].tolist()}, setting {x[off].tolist()}"
            )
        try:
            y = float(machine.read())
        except (ReadError, TimeoutError) as err:
            problems.append(f"{type(err).__name__}: {err}")
            continue
        if not math.isfinite(y):
            problems.append(f"non-finite reading {y}")
            continue
        after = machine_state(machine)
        reasons = []
        off = off_setting(after, x, tol)
        if off:
            reasons.append(
                f"readbacks of knobs {off} left the setting during the reading "
                f"(now {after['readback'][off].tolist()}, setting {x[off].tolist()})"
            )
        if "setpoint" in before and not torch.equal(before["setpoint"], after["setpoint"]):
            changed = (before["setpoint"] != after["setpoint"]).nonzero().flatten().tolist()
            reasons.append(
                f"setpoints of knobs {changed} changed during the reading "
                f"({before['setpoint'][changed].tolist()} -> {after['setpoint'][changed].tolist()})"
            )
        if after.get("disconnections", 0) != before.get("disconnections", 0):
            n = after["disconnections"] - before["disconnections"]
            reasons.append(f"{n} channel disconnection(s) during the reading")
        if not reasons:
            return y, attempt
        reason = "; ".join(reasons)
        on_discard(reason, y)
        problems.append(f"discarded: {reason}")
        if off:
            raise MachineError(f"reading discarded and the knobs moved: {reason}")
    raise ReadError(f"no valid reading in {retries + 1} attempts ({'; '.join(problems)})")


def restore_knobs(
    machine,
    target: torch.Tensor,
    bounds,
    limit,
    *,
    attempts: int,
    interval: float,
    readback_tol: float,
    on_set,
) -> tuple[BaseException | None, int, list[str]]:
    r"""Ramp ``machine`` to ``target`` and verify the readback (:func:`verify_readback`), up to
    ``attempts`` times ``interval`` seconds apart (each attempt ramps from where the knobs then
    are); a ``KeyboardInterrupt`` (a second signal) abandons it.

    Returns:
        ``(error, attempts_made, attempt_errors)``: the last error (``None``: restored), the
        attempts made and one line per failed attempt.
    """
    error, made, errors = None, 0, []
    for attempt in range(1, attempts + 1):
        made = attempt
        try:
            move(machine, target, bounds, limit, ramp=True, on_set=on_set)
            verify_readback(machine, target, bounds, readback_tol)
            return None, made, errors
        except KeyboardInterrupt as err:  # a second signal: abandon the restore
            errors.append(f"{type(err).__name__}: {err}")
            return err, made, errors
        except Exception as err:  # reported by the caller, never hides the run's error
            error = err
            errors.append(f"{type(err).__name__}: {err}")
            if attempt < attempts and interval > 0:
                try:
                    time.sleep(float(interval))
                except KeyboardInterrupt as err2:
                    return err2, made, errors
    return error, made, errors
