r"""The optimization loop: measure the start point, then ask -> evaluate -> tell until the budget.

The loop is the only place that talks to both an optimizer and a machine; it records every
evaluation in a tidy table (and, optionally, in a :class:`~pigp_torch.runlog.RunLog` on disk) and,
on a :class:`~pigp_torch.machine.base.Machine`, enforces the safety rules below.

**Safety rules on a machine** (any :class:`~pigp_torch.machine.base.Machine`, not only EPICS):

1. *Bounds and step limit at the machine boundary.* Every setting the loop sends passes
   :func:`~pigp_torch.machine.base.check_setting` against the machine's ``bounds`` and the step
   limit :math:`m` (the elementwise minimum of the machine's ``max_step`` and the loop's
   ``max_step``), measured from the previous setting sent, *before* ``machine.set`` is called —
   on top of whatever the machine itself checks and of the optimizer's own rules (BayesOpt's trust
   box). A setting that breaks a rule is refused with ``ValueError`` and the run ends as below.
2. *How a proposal is reached* (``moves``). The start point, the first point after a resume and
   every restore are always reached by a ramp: the move :math:`\Delta` is cut into
   :math:`n = \lceil \max_i |\Delta_i| / (0.99\, m_i) \rceil` equal steps on the segment (all
   inside the convex box; the 1 % margin leaves room for a machine that measures the step from
   readbacks sitting within their tolerance of the setpoints). With ``moves="ramp"`` every
   proposal is reached the same way and the objective is read once, after the last step; the
   optimizer's algorithm is untouched, so Nelder–Mead and RCDS, which have no step limit of their
   own, respect the machine's limit, and BayesOpt keeps its trust box (which bounds the distance
   from the best point, not from the last one). With ``moves="set"`` (the default, for
   compatibility) a proposal is one ``set``, refused if it is too far. ``pigp optimize`` ramps.
3. *Invalid readings.* A reading that is NaN or infinite, or a read that raises
   :class:`~pigp_torch.machine.errors.ReadError` or ``TimeoutError``, is retried up to
   ``read_retries`` times, ``retry_interval`` seconds apart; then the run aborts with
   ``ReadError``. (Give a machine that retries on its own, like ``EpicsMachine``, zero retries
   of its own, or the two counts multiply.)
   *Readings checked against the machine's state* (``check_readings``, default on): the knob
   readbacks (``get()``) must lie within the readback tolerance of the setting before *and*
   after each reading (the machine's ``tolerance`` when it has one, else ``readback_tol`` of
   each range); a machine with ``setpoints()`` must show the same setpoints after the reading as
   before, and one with a ``disconnections`` counter must not have lost a connection during it.
   A reading that fails a check is discarded (a ``discarded`` record in the log, with the
   reason and the value) and taken again if the knobs are (still) at the setting, within the
   same ``read_retries``; if the knobs are no longer at the setting (an IOC reboot, another
   client) the run aborts with :class:`~pigp_torch.machine.errors.MachineError`. Freshness of
   the objective (timestamps that must advance) is the machine's check (``EpicsMachine``
   raises a ``StaleReadingError``, a ``ReadError``); what the machine reports about a reading
   (``last_reading``) is stored with the evaluation.
4. *Objective floor.* With ``objective_floor`` set, a valid reading below it is recorded, then the
   run aborts with :class:`RunAborted` (the beam may be gone or being lost).
5. *Restore.* The initial knobs — those found at the start (``get()``), or on a resume those
   logged by the run's *first* start — are put back, by a ramp, when the run ends with any
   exception (a machine error, a refused setting, a bug, ``KeyboardInterrupt`` — Ctrl-C — SIGTERM
   or SIGHUP), and at the end of a completed run unless ``restore="best"`` (the best observed
   point is set) or ``restore="none"``. The target is verified by readback: ``get()`` must be
   within ``readback_tol`` of it. A failed attempt is retried, ``restore_attempts`` in all,
   ``restore_interval`` seconds apart (each attempt ramps from where the knobs then are); the
   end record says whether the knobs were restored and holds the last setpoint written
   (``last_setpoint``). While restoring, SIGINT/SIGTERM/SIGHUP are deferred (a second one
   abandons the restore).
6. *Signals.* With ``handle_signals`` (default) SIGTERM and SIGHUP (terminal closed, SSH
   dropped) raise :class:`Terminated`, a ``KeyboardInterrupt``, so they take the Ctrl-C path:
   restore, then re-raise; a SIGHUP that was ignored when the run started (``nohup``) stays
   ignored. The handlers are installed only in the main thread and the previous ones are always
   put back.
7. *Intent records.* With a log, every ``set`` the loop sends is preceded by an ``intent``
   record (the setting about to be written, the purpose, the step), written and fsynced before
   the write: after a crash (SIGKILL, power cut) the log holds the last commanded setting.

**Run log and resume.** With ``log`` every evaluation is appended (and fsynced) before the next
step, framed by a ``start`` and an ``end`` record (status, reason, where the knobs were put
back and their readback); see :mod:`pigp_torch.runlog`. ``resume=`` continues a logged run: the
optimizer is rebuilt with :func:`~pigp_torch.runlog.replay` and the run goes on at the next step
until ``budget`` evaluations in all; the knobs are restored to the initial knobs of the logged
run's first start (not to where a crash left them), and the new start record notes where the
knobs were found (``found_knobs``).
"""

from __future__ import annotations

import math
import signal
import threading
import time
import warnings
from collections.abc import Callable
from contextlib import contextmanager
from pathlib import Path

import pandas as pd
import torch

from pigp_torch._utils import DTYPE, as_knob_tensor, check_bounds
from pigp_torch._utils import utc_now as _utc_now
from pigp_torch.machine.base import Machine, check_setting, max_step_tensor
from pigp_torch.machine.errors import MachineError, ReadError
from pigp_torch.runlog import RunLog, RunRecords, evaluation_rows, replay

RESTORE_MODES = ("initial", "best", "none")
MOVE_MODES = ("set", "ramp")
_RESERVED = ("step", "y", "method", "ask_time_s", "eval_time_s")
#: Ramp steps are planned at this fraction of the step limit: a machine that measures the step
#: from its readbacks (``EpicsMachine``) sees the readback within its tolerance of the setpoint.
RAMP_FRACTION = 0.99


class RunAborted(RuntimeError):
    """The loop stopped a run on one of its safety rules (the objective fell below its floor)."""


class Terminated(KeyboardInterrupt):
    """SIGTERM or SIGHUP arrived during a run; handled like Ctrl-C (knobs restored, then
    re-raised).

    Attributes:
        signum: the signal number (``signal.SIGTERM`` or ``signal.SIGHUP``).
    """

    def __init__(self, message: str = "", signum: int = signal.SIGTERM) -> None:
        super().__init__(message)
        self.signum = int(signum)


#: Signals that end a run like SIGTERM (where the platform has them).
_TERMINATING = tuple(s for s in (signal.SIGTERM, getattr(signal, "SIGHUP", None)) if s is not None)


def _knob_columns(knob_names, objective, d: int) -> list[str]:
    if knob_names is None:
        knob_names = getattr(objective, "knob_names", None)
    names = [f"x{i}" for i in range(d)] if knob_names is None else [str(n) for n in knob_names]
    if len(names) != d:
        raise ValueError(f"{len(names)} knob names for {d} knobs")
    if len(set(names)) != d:
        raise ValueError("knob names must be unique")
    clash = sorted(set(names) & set(_RESERVED))
    if clash:
        raise ValueError(f"knob names {clash} clash with the table columns {_RESERVED}")
    return names


# ---------------------------------------------------------------------------------- signals
class _SignalGuard:
    r"""SIGTERM/SIGHUP -> :class:`Terminated` during a run; all three deferred while restoring.

    Installed for the whole of :func:`optimize` (main thread only; otherwise a no-op), the
    previous handlers are put back on exit. While ``deferring`` is false, SIGTERM or SIGHUP raise
    :class:`Terminated` and SIGINT goes to the previous handler (Python's default raises
    ``KeyboardInterrupt``; an ignored SIGINT stays ignored). While ``deferring`` is true (the
    restore and the end record), signals are only recorded in ``deferred``; a second one raises
    ``KeyboardInterrupt`` — the way out of a restore that hangs. Inside :meth:`held` a signal
    acts only when the block ends.
    """

    SIGNALS = (signal.SIGINT, *_TERMINATING)

    def __init__(self, enabled: bool) -> None:
        self.enabled = bool(enabled) and threading.current_thread() is threading.main_thread()
        self.deferring = False
        self.deferred: list[str] = []
        self._previous: dict = {}
        self._holding = False
        self._held: list = []

    def _handler(self, signum, frame) -> None:
        name = signal.Signals(signum).name
        if self._holding:
            self._held.append((signum, frame))
            return
        if self.deferring:
            self.deferred.append(name)
            if len(self.deferred) >= 2:
                raise KeyboardInterrupt(f"second signal ({name}) during the restore: abandoned")
            return
        self._act(signum, frame)

    def _act(self, signum, frame) -> None:
        if signum in _TERMINATING:
            raise Terminated(f"received {signal.Signals(signum).name}", signum)
        previous = self._previous.get(signum)
        if callable(previous):
            previous(signum, frame)
        elif previous != signal.SIG_IGN:
            raise KeyboardInterrupt

    @contextmanager
    def held(self):
        """Signals arriving inside the block act when it ends, so the block is never cut in two
        (used to write an evaluation to the log and to the table together)."""
        self._holding = True
        try:
            yield
        finally:
            self._holding = False
            held, self._held = self._held, []
            if held:
                self._act(*held[0])

    def __enter__(self) -> _SignalGuard:
        if self.enabled:
            for s in self.SIGNALS:
                if (
                    s != signal.SIGINT
                    and s != signal.SIGTERM
                    and signal.getsignal(s) == signal.SIG_IGN
                ):
                    continue  # SIGHUP ignored on purpose (nohup): the run goes on
                self._previous[s] = signal.signal(s, self._handler)
        return self

    def __exit__(self, *exc) -> None:
        for s, h in self._previous.items():
            signal.signal(s, h if h is not None else signal.SIG_DFL)
        self._previous.clear()


def _classify(err: BaseException) -> tuple[str, str]:
    """``(status, reason)`` of the end record for an exception that ended a run."""
    if isinstance(err, Terminated):
        return "interrupted", f"Terminated ({err})"
    if isinstance(err, KeyboardInterrupt):
        return "interrupted", f"KeyboardInterrupt (Ctrl-C / SIGINT){f': {err}' if str(err) else ''}"
    if isinstance(err, (MachineError, RunAborted)):
        return "aborted", f"{type(err).__name__}: {err}"
    return "failed", f"{type(err).__name__}: {err}"


# ---------------------------------------------------------------------------------- moves
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


def _move(machine, target: torch.Tensor, bounds, limit, *, ramp: bool, on_set=None) -> int:
    r"""Send ``target`` to ``machine``: one checked ``set``, or a checked ramp; returns the sets.

    Every setting passes :func:`check_setting` (bounds; step from the previous setting sent, the
    first measured from ``machine.get()``) before ``machine.set``; ``on_set(x, k, n)`` (if given)
    is called just before the ``k``-th of ``n`` sets (the intent record).
    """
    target = check_setting(target, bounds)
    previous = torch.as_tensor(machine.get(), dtype=DTYPE).reshape(-1)
    n = 1
    if ramp and limit is not None:
        planned = limit * RAMP_FRACTION
        n = max(1, math.ceil(float(((target - previous).abs() / planned).max()) - 1e-9))
    start, delta = previous.clone(), target - previous
    for k in range(1, n + 1):
        x = target if k == n else start + delta * (k / n)
        # intermediate points are convex combinations; the clamp only removes round-off
        x = torch.minimum(torch.maximum(x, bounds[0]), bounds[1])
        x = check_setting(x, bounds, current=previous, max_step=limit)
        if on_set is not None:
            on_set(x, k, n)
        machine.set(x.clone())
        previous = x
    return n


def _verify_readback(machine, target: torch.Tensor, bounds, readback_tol: float) -> torch.Tensor:
    got = torch.as_tensor(machine.get(), dtype=DTYPE).reshape(-1)
    tol = readback_tol * (bounds[1] - bounds[0])
    bad = ((got - target).abs() > tol).nonzero().flatten().tolist()
    if bad:
        raise MachineError(
            f"readback check failed on knob indices {bad}: read {got[bad].tolist()}, "
            f"expected {target[bad].tolist()} (tolerance {tol[bad].tolist()})"
        )
    return got


def _read(measure: Callable[[], float], retries: int, interval: float) -> tuple[float, int]:
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


def _machine_state(machine) -> dict:
    """What a reading is checked against: readbacks, setpoints and the disconnection count
    (the latter two only where the machine offers them)."""
    state = {"readback": torch.as_tensor(machine.get(), dtype=DTYPE).reshape(-1)}
    setpoints = getattr(machine, "setpoints", None)
    if callable(setpoints):
        state["setpoint"] = torch.as_tensor(setpoints(), dtype=DTYPE).reshape(-1)
    if hasattr(machine, "disconnections"):
        state["disconnections"] = int(machine.disconnections)
    return state


def _off_setting(state: dict, x: torch.Tensor, tol: torch.Tensor) -> list[int]:
    return ((state["readback"] - x).abs() > tol).nonzero().flatten().tolist()


def _checked_read(
    machine, x: torch.Tensor, tol: torch.Tensor, retries: int, interval: float, on_discard
) -> tuple[float, int]:
    r"""A valid reading of ``machine`` at setting ``x``, checked against the machine's state.

    Before each attempt the readbacks must be within ``tol`` of ``x`` (else ``MachineError``);
    after it, the readbacks must still be there, the setpoints unchanged and no connection lost.
    A reading that fails the after-check is reported to ``on_discard(reason, y)`` and taken
    again (within the ``retries + 1`` attempts) if the knobs are still at ``x``; otherwise
    ``MachineError``. Invalid readings are retried as in :func:`_read`.

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
        before = _machine_state(machine)
        off = _off_setting(before, x, tol)
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
        after = _machine_state(machine)
        reasons = []
        off = _off_setting(after, x, tol)
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


# ---------------------------------------------------------------------------------- the loop
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
    restore: str = "initial",
    moves: str = "set",
    max_step=None,
    read_retries: int = 2,
    retry_interval: float = 0.0,
    objective_floor: float | None = None,
    log: RunLog | str | Path | None = None,
    resume: RunRecords | list[dict] | None = None,
    handle_signals: bool = True,
    readback_tol: float = 1e-3,
    restore_attempts: int = 3,
    restore_interval: float = 1.0,
    check_readings: bool = True,
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
        restore: ``"initial"``, ``"best"`` or ``"none"``.
        moves: ``"set"`` (one ``set`` per proposal) or ``"ramp"`` (ramp to every proposal).
        max_step: a step limit of the loop on top of the machine's ``max_step`` (scalar fraction
            of each knob's half-range or ``d`` absolute, see
            :func:`~pigp_torch.machine.base.max_step_tensor`), or ``None``.
        read_retries: extra read attempts after an invalid reading (>= 0).
        retry_interval: seconds to wait before each extra attempt (>= 0).
        objective_floor: abort when a reading falls below this value (``None``: no floor).
        log: a :class:`~pigp_torch.runlog.RunLog` (left open), or a path: a new log is created
            (or, when resuming, the log is continued) and closed at the end.
        resume: the records of a logged run (:func:`~pigp_torch.runlog.read_log`) or its
            evaluation records; ``optimizer`` must be fresh and built as in that run.
        handle_signals: turn SIGTERM and SIGHUP into :class:`Terminated` during the run, and
            defer SIGINT/SIGTERM/SIGHUP while restoring (main thread only).
        readback_tol: allowed ``|get() - target|`` after a restore, a fraction of each knob's
            range (and around a reading, for a machine without a ``tolerance`` of its own).
        restore_attempts: attempts at the restore (ramp and readback check, >= 1; default 3).
        restore_interval: seconds between those attempts (>= 0; default 1).
        check_readings: check every reading of a machine against its state (rule 3).

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
        pigp_torch.runlog.ReplayError: the resumed log does not match the optimizer.
    """
    if int(budget) != budget or budget < 1:
        raise ValueError(f"budget must be a positive integer, got {budget}")
    budget = int(budget)
    if restore not in RESTORE_MODES:
        raise ValueError(f"restore must be one of {RESTORE_MODES}, got {restore!r}")
    if moves not in MOVE_MODES:
        raise ValueError(f"moves must be one of {MOVE_MODES}, got {moves!r}")
    if int(read_retries) != read_retries or read_retries < 0:
        raise ValueError(f"read_retries must be an integer >= 0, got {read_retries}")
    read_retries = int(read_retries)
    if not (0.0 <= float(retry_interval) < float("inf")):
        raise ValueError(f"retry_interval must be finite and >= 0, got {retry_interval}")
    retry_interval = float(retry_interval)
    if objective_floor is not None and not math.isfinite(float(objective_floor)):
        raise ValueError(f"objective_floor must be finite or None, got {objective_floor}")
    if not (0.0 <= float(readback_tol) < float("inf")):
        raise ValueError(f"readback_tol must be finite and >= 0, got {readback_tol}")
    if int(restore_attempts) != restore_attempts or restore_attempts < 1:
        raise ValueError(f"restore_attempts must be an integer >= 1, got {restore_attempts}")
    restore_attempts = int(restore_attempts)
    if not (0.0 <= float(restore_interval) < float("inf")):
        raise ValueError(f"restore_interval must be finite and >= 0, got {restore_interval}")
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

    x_found = torch.as_tensor(objective.get(), dtype=DTYPE).clone() if is_machine else None
    x_initial = x_found
    logged_initial = _logged_initial_knobs(resume)
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
    names = _knob_columns(knob_names, objective, d)
    label = method if method is not None else getattr(optimizer, "name", type(optimizer).__name__)
    maximize = bool(getattr(optimizer, "maximize", True))
    if isinstance(resume, RunRecords) and resume.knob_names and resume.knob_names != names:
        raise ValueError(f"the resumed log has knobs {resume.knob_names}, the run has {names}")

    bounds = limit = None
    if is_machine:
        bounds = check_bounds(objective.bounds)
        if bounds.shape[1] != d:
            raise ValueError(f"the machine has {bounds.shape[1]} knobs, the optimizer {d}")
        limit = effective_max_step(objective, bounds, max_step)
        if x_initial is not x_found:
            try:
                check_setting(x_initial, bounds)
            except ValueError as err:
                raise ValueError(f"the logged initial knobs are not allowed: {err}") from err
        machine_tol = getattr(objective, "tolerance", None)
        if machine_tol is not None:
            read_tol = torch.as_tensor(machine_tol, dtype=DTYPE).expand(d).clone()
        else:
            read_tol = float(readback_tol) * (bounds[1] - bounds[0])
    sent = {"last": None, "step": None, "purpose": "evaluation"}

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

    def evaluate(x: torch.Tensor, ramp: bool, step: int) -> tuple[float, int]:
        if is_machine:
            sent["step"], sent["purpose"] = step, "evaluation"
            _move(objective, x, bounds, limit, ramp=ramp, on_set=on_set)
            if not check_readings:
                return _read(objective.read, read_retries, retry_interval)

            def on_discard(reason: str, y: float) -> None:
                if log is not None:
                    log.write("discarded", step=step, y=y, reason=reason, time=_utc_now())

            return _checked_read(objective, x, read_tol, read_retries, retry_interval, on_discard)
        return _read(lambda: objective(x), read_retries, retry_interval)

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
    with _SignalGuard(handle_signals) as guard:
        error, status, reason = None, "completed", ""
        try:
            if logged:
                replay(optimizer, logged, progress=progress)
                rows = evaluation_rows(logged, names, label)
            _run_steps(
                evaluate,
                optimizer,
                x0,
                len(rows),
                budget,
                rows,
                names=names,
                label=label,
                moves=moves,
                log=log,
                x_initial=x_initial,
                x_found=x_found,
                reading_info=(lambda: getattr(objective, "last_reading", None)),
                callback=callback,
                progress=progress,
                objective_floor=objective_floor,
                guard=guard,
            )
        except BaseException as err:
            error = err
            status, reason = _classify(err)
        finally:
            guard.deferring = True  # from here on: restore and end record, signals deferred

        best = _best(rows, names, maximize)
        restored_to, final_knobs, restore_error = "none", None, None
        restored, attempts_made, attempt_errors = True, 0, []
        if is_machine:
            # initial knobs after any failure; initial / best / none after a completed run
            mode = restore if error is None else ("none" if restore == "none" else "initial")
            if mode != "none":
                target = x_initial if mode == "initial" else torch.tensor(best["x"], dtype=DTYPE)
                sent["purpose"], sent["step"] = f"restore {mode}", None
                for attempt in range(1, restore_attempts + 1):
                    attempts_made = attempt
                    try:
                        _move(objective, target, bounds, limit, ramp=True, on_set=on_set)
                        _verify_readback(objective, target, bounds, float(readback_tol))
                        restore_error = None
                        break
                    except KeyboardInterrupt as err:  # a second signal: abandon the restore
                        restore_error = err
                        attempt_errors.append(f"{type(err).__name__}: {err}")
                        break
                    except Exception as err:  # reported below, never hides the run's error
                        restore_error = err
                        attempt_errors.append(f"{type(err).__name__}: {err}")
                        if attempt < restore_attempts and restore_interval > 0:
                            try:
                                time.sleep(float(restore_interval))
                            except KeyboardInterrupt as err2:
                                restore_error = err2
                                break
                restored = restore_error is None
                restored_to = mode if restored else f"{mode} (failed)"
            try:
                final_knobs = torch.as_tensor(objective.get(), dtype=DTYPE).reshape(-1).tolist()
            except Exception as err:  # the readback itself failed: say so in the log
                final_knobs = f"unavailable: {type(err).__name__}: {err}"
        if error is None and restore_error is not None:
            status, reason = _classify(restore_error)
            reason = f"restoring the knobs failed: {reason}"

        if log is not None:
            try:
                end = {"restored_to": restored_to, "final_knobs": final_knobs}
                end.update(n_evaluations=len(rows), best=best)
                if is_machine:
                    end.update(restored=restored, last_setpoint=sent["last"])
                    end.update(restore_attempts=attempts_made)
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
                f"attempt(s)): {restore_error!r}; last setpoint written: {sent['last']}",
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


def _logged_initial_knobs(resume) -> torch.Tensor | None:
    """The initial knobs of a resumed run's first start record (``None`` if not logged)."""
    if not isinstance(resume, RunRecords):
        return None
    for start in resume.starts:
        knobs = start.get("initial_knobs")
        if knobs is not None:
            return torch.tensor([float(v) for v in knobs], dtype=DTYPE)
    return None


def _best(rows: list[dict], names: list[str], maximize: bool) -> dict | None:
    """``{"step", "x", "y"}`` of the best row (first on ties), ``None`` without rows."""
    if not rows:
        return None
    ys = torch.tensor([r["y"] for r in rows], dtype=DTYPE)
    b = rows[int(ys.argmax() if maximize else ys.argmin())]
    return {"step": b["step"], "x": [b[n] for n in names], "y": b["y"]}


def _run_steps(
    evaluate,
    optimizer,
    x0,
    first,
    budget,
    rows,
    *,
    names,
    label,
    moves,
    log,
    x_initial,
    x_found,
    reading_info,
    callback,
    progress,
    objective_floor,
    guard: _SignalGuard,
) -> None:
    """Steps ``first .. budget-1`` of :func:`optimize`; appends to ``rows`` as it goes."""
    if log is not None:
        extra = {}
        if x_found is not None and x_found is not x_initial:
            extra["found_knobs"] = x_found.tolist()
        log.log_start(x_initial, budget=budget, first_step=first, **extra)
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=budget, initial=first, desc=str(label))
    try:
        x = x0
        seen = len(getattr(optimizer, "notices", ()))  # notices of a replay are not repeated
        for step in range(first, budget):
            t_set = time.time()
            ask_time = 0.0
            notices: list[dict] = []
            if step > 0:
                t0 = time.perf_counter()
                x = torch.as_tensor(optimizer.ask(), dtype=DTYPE).reshape(-1)
                ask_time = time.perf_counter() - t0
                notices = list(getattr(optimizer, "notices", ())[seen:])
                seen += len(notices)
            if log is not None:
                for notice in notices:  # the optimizer's own findings, before the move
                    log.write("notice", step=step, time=_utc_now(), **notice)
            t0 = time.perf_counter()
            # the start point and the first point of a resumed run are always ramped to
            y, reads = evaluate(x, ramp=(moves == "ramp" or step == first), step=step)
            info = reading_info()
            eval_time = time.perf_counter() - t0
            row = {"step": step, **dict(zip(names, x.tolist(), strict=True))}
            row.update(y=y, method=label, ask_time_s=ask_time, eval_time_s=eval_time)
            if notices:
                row["notices"] = [n["message"] for n in notices]
            with guard.held():  # a signal never splits the log record from the table row
                if log is not None:  # on disk before the optimizer hears of it
                    log.log_evaluation(
                        step,
                        x,
                        y,
                        reads=reads,
                        t_set=t_set,
                        t_read=time.time(),
                        ask_time_s=ask_time,
                        eval_time_s=eval_time,
                        **({"reading": info} if isinstance(info, dict) else {}),
                    )
                rows.append(row)
            t0 = time.perf_counter()
            optimizer.tell(x, y)
            row["ask_time_s"] = ask_time + (time.perf_counter() - t0)
            if callback is not None:
                callback(dict(row))
            if bar is not None:
                bar.update(1)
            if objective_floor is not None and y < objective_floor:
                raise RunAborted(
                    f"objective {y:.6g} at step {step} is below the floor {objective_floor:g}"
                )
    finally:
        if bar is not None:
            bar.close()
