r"""At the machine boundary: checked settings and ramps within the step limit, readback checks,
bounded read retries, readings checked against the machine's state, and the restore.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

import torch

from pigp_torch._utils import DTYPE, max_step_tensor
from pigp_torch.loop.readings import plausible_reading
from pigp_torch.machine.base import check_setting, ramp_steps, setpoints_of
from pigp_torch.machine.errors import MachineError, ReadbackError

#: Ramp steps are planned at this fraction of the step limit: a machine that measures the step
#: from its readbacks (``EpicsMachine``) sees the readback within its tolerance of the setpoint.
RAMP_FRACTION = 0.99
#: A setpoint equals its target within this fraction of the knob's range (round-off only).
SETPOINT_TOL = 1e-9
#: Least pause (s) between the restore's attempts beyond ``restore_attempts`` (its window).
WINDOW_PAUSE_S = 0.2


def effective_max_step(machine, bounds: torch.Tensor, max_step) -> torch.Tensor | None:
    """Elementwise minimum of the machine's and the loop's step limits (absolute, ``d``)."""
    limits = [max_step_tensor(m, bounds) for m in (machine.max_step, max_step) if m is not None]
    if not limits:
        return None
    out = limits[0]
    for m in limits[1:]:
        out = torch.minimum(out, m)
    return out


def move(
    machine,
    target: torch.Tensor,
    bounds,
    limit,
    *,
    on_set=None,
    on_ack=None,
    readback_errors: list[str] | None = None,
) -> int:
    r"""Send ``target`` to ``machine`` by a checked ramp; returns the number of sets.

    The move starts from the machine's setpoints (:func:`setpoints_of`: what the IOC holds,
    never a readback). Every setting passes :func:`check_setting` (bounds; step from the
    previous setting) before ``machine.set``; ``on_set(x, k, n)`` (if given) is called just
    before the ``k``-th of ``n`` sets (the intent record), ``on_ack(x)`` after a set that
    returned (its puts acknowledged). With ``readback_errors`` (a list; used by the restore) a
    :class:`~pigp_torch.machine.errors.ReadbackError` — raised by a machine after its puts
    completed, when a readback does not follow — is appended there and the ramp goes on, so the
    setpoints still reach ``target`` step by step.
    """
    target = check_setting(target, bounds)
    previous = setpoints_of(machine)
    planned = limit * RAMP_FRACTION if limit is not None else None
    steps = ramp_steps(previous, target, planned)
    for k, x in enumerate(steps, start=1):
        # intermediate points are convex combinations; the clamp only removes round-off
        x = torch.minimum(torch.maximum(x, bounds[0]), bounds[1])
        x = check_setting(x, bounds, current=previous, max_step=limit)
        if on_set is not None:
            on_set(x, k, len(steps))
        try:
            machine.set(x.clone())
        except ReadbackError as err:  # raised after the puts were acknowledged
            if on_ack is not None:
                on_ack(x)
            if readback_errors is None:
                raise
            readback_errors.append(f"{type(err).__name__}: {err}")
        else:
            if on_ack is not None:
                on_ack(x)
        previous = x
    return len(steps)


def verify_readback(
    machine, target: torch.Tensor, bounds, readback_tol: float, reference=None
) -> torch.Tensor:
    r"""Check that the knobs are at ``target``: the setpoints (where the machine has
    ``setpoints()``) equal to ``target`` within :data:`SETPOINT_TOL` of each range, and every
    readback within ``readback_tol`` of the range of ``target`` — or, with ``reference`` (the
    readbacks found at the start, when ``target`` is where the run found the setpoints), of its
    reference (a readback offset the knob already had). Returns the readbacks.

    Raises:
        MachineError: naming the knobs, their setpoints or readbacks, and the target.
    """
    width = bounds[1] - bounds[0]
    setpoints = machine.setpoints()
    if setpoints is not None:
        sp = torch.as_tensor(setpoints, dtype=DTYPE).reshape(-1)
        bad = ((sp - target).abs() > SETPOINT_TOL * width).nonzero().flatten().tolist()
        if bad:
            raise MachineError(
                f"setpoint check failed on knob indices {bad}: setpoints {sp[bad].tolist()}, "
                f"target {target[bad].tolist()}"
            )
    got = torch.as_tensor(machine.get(), dtype=DTYPE).reshape(-1)
    tol = readback_tol * width
    off = (got - target).abs() > tol
    if reference is not None:
        off &= (got - torch.as_tensor(reference, dtype=DTYPE)).abs() > tol
    bad = off.nonzero().flatten().tolist()
    if bad:
        raise MachineError(
            f"readback check failed on knob indices {bad}: read {got[bad].tolist()}, "
            f"expected {target[bad].tolist()} (tolerance {tol[bad].tolist()})"
        )
    return got


def read(
    measure: Callable[[], float],
    retries: int,
    interval: float,
    judge=None,
    on_discard=None,
    parts=None,
) -> tuple[float, int]:
    """A valid reading and the number of attempts it took (:func:`plausible_reading` with
    ``judge``, default: finite only, and ``parts``); ``ReadError`` after ``retries + 1``
    invalid ones (``interval`` seconds apart)."""
    return plausible_reading(
        measure, judge, retries, interval, on_discard or (lambda reason, y: None), parts
    )


def machine_state(machine) -> dict:
    """What a reading is checked against: readbacks, setpoints and the disconnection count
    (the latter two only where the machine offers them)."""
    state = {"readback": torch.as_tensor(machine.get(), dtype=DTYPE).reshape(-1)}
    setpoints = machine.setpoints()
    if setpoints is not None:
        state["setpoint"] = torch.as_tensor(setpoints, dtype=DTYPE).reshape(-1)
    if machine.disconnections is not None:
        state["disconnections"] = int(machine.disconnections)
    return state


def off_setting(state: dict, x: torch.Tensor, tol: torch.Tensor) -> list[int]:
    return ((state["readback"] - x).abs() > tol).nonzero().flatten().tolist()


def checked_take(machine, x: torch.Tensor, tol: torch.Tensor, on_discard) -> float | None:
    r"""One reading of ``machine`` at setting ``x``, checked against the machine's state.

    Before the reading the readbacks must be within ``tol`` of ``x`` (else ``MachineError``);
    after it, the readbacks must still be there, the setpoints unchanged and no connection
    lost. A reading that fails the after-check is reported to ``on_discard(reason, y)`` and
    ``None`` is returned if the knobs are still at ``x`` (the caller reads again); otherwise
    ``MachineError``. A read that raises ``ReadError``/``TimeoutError`` passes it on.
    """
    before = machine_state(machine)
    off = off_setting(before, x, tol)
    if off:
        raise MachineError(
            f"knobs {off} are not at the setting before the reading: readback "
            f"{before['readback'][off].tolist()}, setting {x[off].tolist()}"
        )
    y = float(machine.read())
    if not math.isfinite(y):
        return y  # retried by the caller
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
        return y
    reason = "; ".join(reasons)
    on_discard(reason, y)
    if off:
        raise MachineError(f"reading discarded and the knobs moved: {reason}")
    return None


def checked_read(
    machine,
    x: torch.Tensor,
    tol: torch.Tensor,
    retries: int,
    interval: float,
    on_discard,
    judge=None,
) -> tuple[float, int]:
    r"""A valid reading of ``machine`` at setting ``x``, checked against the machine's state
    (:func:`checked_take`) and, with ``judge``, plausible
    (:func:`~pigp_torch.loop.readings.plausible_reading`).

    Returns:
        ``(y, attempts)``.

    Raises:
        MachineError: the knobs are not (or no longer) at ``x``.
        ReadError: no valid, consistent reading in ``retries + 1`` attempts.
    """
    return plausible_reading(
        lambda: checked_take(machine, x, tol, on_discard), judge, retries, interval, on_discard,
        parts=lambda: averaged_parts(machine),
    )  # fmt: skip


def averaged_parts(machine) -> list | None:
    """The single readings a machine averaged into its last reading (``last_reading["values"]``
    where it reports them, as ``EpicsMachine`` does), else ``None``."""
    info = machine.last_reading
    return info.get("values") if isinstance(info, dict) else None


def _ramp_each(machine, target, bounds, limit, on_set, on_ack, readback_errors) -> list[str]:
    """Ramp every knob not at its ``target`` setpoint on its own (the others held where the
    machine holds them), so that a knob the machine refuses does not stop the others; returns
    one line per knob that failed (named where the machine names its knobs). Setpoints that
    cannot be read stop it (raised: no knob can be moved then)."""
    names = list(machine.knob_names or [])
    width = bounds[1] - bounds[0]
    failures = []
    for i in range(target.numel()):
        name = names[i] if i < len(names) else f"knob {i}"
        goal = setpoints_of(machine).clone()  # unreadable setpoints: no knob can go (raised)
        if abs(float(goal[i] - target[i])) <= SETPOINT_TOL * float(width[i]):
            continue
        try:
            goal[i] = target[i]
            move(machine, goal, bounds, limit, on_set=on_set, on_ack=on_ack,
                 readback_errors=readback_errors)  # fmt: skip
        except Exception as err:  # this knob only; a KeyboardInterrupt stops the restore
            failures.append(f"{name}: {type(err).__name__}: {err}")
    return failures


def _ramp_all_then_each(machine, target, bounds, limit, on_set, on_ack, readback_errors):
    """One ramp of every knob together; when it fails, :func:`_ramp_each`. Returns ``None``, or
    the joint ramp's error when the knobs then went one by one.

    Raises:
        MachineError: a knob could not be ramped on its own either (every one named).
    """
    try:
        move(machine, target, bounds, limit, on_set=on_set, on_ack=on_ack,
             readback_errors=readback_errors)  # fmt: skip
        return None
    except Exception as err:  # every knob on its own: one refusal must not stop the others
        first = f"{type(err).__name__}: {err}"
    try:
        failed = _ramp_each(machine, target, bounds, limit, on_set, on_ack, readback_errors)
    except Exception as err:
        raise MachineError(f"{first}; then knob by knob: {type(err).__name__}: {err}") from err
    if failed:
        raise MachineError(f"{first}; then knob by knob: " + "; ".join(failed))
    return f"{first} (then ramped knob by knob)"


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
    on_ack=None,
    reference=None,
    window: float = 0.0,
) -> tuple[BaseException | None, int, list[str]]:
    r"""Ramp ``machine``'s setpoints to ``target`` and verify them and the readbacks
    (:func:`verify_readback`), ``interval`` seconds apart, until ``attempts`` attempts were made
    and ``window`` seconds (the run's ``restore_timeout``) have passed since the first began —
    so an IOC that answers again within the window is restored. Each attempt ramps from the
    setpoints the machine then holds, every knob together; when that fails (a put refused, a
    put never answered) every knob not yet at its target is ramped on its own, so one knob the
    machine refuses does not keep the others from their targets. A readback that does not follow
    does not stop a ramp (:func:`move` with ``readback_errors``), it fails the check at the end;
    a ``KeyboardInterrupt`` (a second signal) abandons the restore.

    Returns:
        ``(error, attempts_made, attempt_errors)``: the last error (``None``: restored), the
        attempts made and one line per failed attempt.
    """
    error, made, errors = None, 0, []
    began = time.monotonic()
    while True:
        made += 1
        readback_errors: list[str] = []
        try:
            joint = _ramp_all_then_each(
                machine, target, bounds, limit, on_set, on_ack, readback_errors
            )
            if joint is not None:  # the end record says the joint ramp failed
                errors.append(joint)
            verify_readback(machine, target, bounds, readback_tol, reference)
            return None, made, errors
        except KeyboardInterrupt as err:  # a second signal: abandon the restore
            errors.append(f"{type(err).__name__}: {err}")
            return err, made, errors
        except Exception as err:  # reported by the caller, never hides the run's error
            error = err
            during = f" (during the ramp: {readback_errors[-1]})" if readback_errors else ""
            line = f"{type(err).__name__}: {err}{during}"
            if not errors or errors[-1] != line:  # a window of retries: each error once
                errors.append(line)
        pause = float(interval) if made < attempts else max(float(interval), WINDOW_PAUSE_S)
        if made >= attempts and time.monotonic() - began + pause >= window:
            return error, made, errors
        try:
            time.sleep(pause)
        except KeyboardInterrupt as err2:
            return err2, made, errors
