r"""An accelerator behind EPICS Channel Access: knob setpoints/readbacks and an objective PV.

:class:`EpicsMachine` implements the :class:`~pigp_torch.machine.base.Machine` protocol over
Channel Access (CA), so :func:`pigp_torch.optimize` drives a control system exactly as it drives
:class:`~pigp_torch.machine.SimulatedMachine`.

**A set** (:meth:`EpicsMachine.set`):

1. the requested setting is checked *before anything is written*
   (:meth:`GuardedMachine.set <pigp_torch.machine.base.GuardedMachine.set>`:
   :math:`\ell \le x \le h` and, with ``max_step``, :math:`|x - x_\mathrm{sp}| \le m` per knob,
   where :math:`x_\mathrm{sp}` are the *setpoint* PVs read just before — the setpoints the IOC
   holds, never the readbacks, so a readback offset or a stuck readback cannot widen a step);
2. the setpoints that change are written in parallel with put-completion (``WriteNotify``)
   and every completion must arrive within ``timeout`` (a put the IOC refuses raises
   :class:`~pigp_torch.machine.errors.PutRefused` naming it); each completed put updates
   :attr:`EpicsMachine.last_acknowledged` (per knob), so after a failure it holds what the IOC
   really received;
3. after ``settle_time`` the readbacks are polled (every 50 ms, for at most ``timeout``) until
   :math:`|x_\mathrm{rb} - x| \le \tau` for every knob, else :class:`ReadbackError`. The default
   tolerance is :math:`\tau_i = 10^{-6}(h_i - \ell_i) + 10^{-9}` (knob units): a relative part
   for round-off in the IOC or in a unit conversion, and an absolute floor for knobs with a
   tiny range. On a real magnet, whose readback carries noise, pass a ``tolerance`` of a few
   readback noise standard deviations.

**A read** (:meth:`EpicsMachine.read`) is the mean of ``n_average`` readings of the objective PV,
``average_interval`` seconds apart (use at least the PV's update period, or the readings repeat).
*Freshness:* each reading is read with its CA timestamp, which must be newer than that of the
previous valid reading (of this read or an earlier one); while it is not, the PV is read again
every ``stale_poll`` seconds, for at most ``stale_timeout`` seconds, then
:class:`StaleReadingError` (a ``ReadError``: a frozen objective PV never yields a reading).
:attr:`EpicsMachine.last_reading` describes the last read (timestamps, polls of stale values).
A reading that is NaN/inf, times out or finds the channel disconnected is retried, up to
``read_retries`` times, ``retry_interval`` seconds apart; then :class:`ReadError`. A reading
(objective, readback, observable) of alarm severity ``refuse_severity`` (``INVALID``) or worse
is not valid (:class:`SeverityError`, naming the PV; a readback: not yet at its setpoint).
**get** returns the knob readbacks read over CA at that moment (never a cached value);
:meth:`setpoints` the setpoint PVs likewise. :attr:`EpicsMachine.objective_limits` is the
objective PV's range (``DRVL``/``DRVH``, else ``LOPR``/``HOPR``; ``None`` where it has neither),
which the loop takes as the default physical range of a reading.
:attr:`EpicsMachine.disconnections` counts the channel disconnections seen since the machine
connected (a reboot of the IOC, a network cut); the loop discards a reading during which it
changed.

**Control limits.** At connection the setpoint PVs' control limits (``DRVL``/``DRVH``, else the
display limits ``LOPR``/``HOPR`` when the control limits are unset, i.e. both 0) are read; bounds
outside them are refused with ``ValueError`` (the IOC would refuse such puts in the middle of a
run). :attr:`EpicsMachine.control_limits` holds them (NaN where a PV has none). Every failure of the
control system surfaces as a :class:`~pigp_torch.machine.errors.MachineError` subclass, which
the loop answers by putting the initial knobs back.

**Client library:** caproto's, behind the adapter named by ``_adapter_class``
(:mod:`~pigp_torch.machine.ca_adapter`; pvAccess: :class:`pigp_torch.machine.pva.PvaMachine`).

Network configuration is EPICS's usual environment: ``EPICS_CA_ADDR_LIST``
(e.g. ``"127.0.0.1:5064"``) and ``EPICS_CA_AUTO_ADDR_LIST=NO`` to search only given hosts.
"""

from __future__ import annotations

import math
import time

import torch

from pigp_torch._utils import DTYPE, check_bounds
from pigp_torch.machine.base import GuardedMachine, check_setting, max_step_tensor
from pigp_torch.machine.ca_adapter import CaprotoAdapter, refuse_outside_control_limits
from pigp_torch.machine.epics_reads import ObjectiveReader, StaleReadingError  # noqa: F401
from pigp_torch.machine.errors import MachineError, ReadbackError, SeverityError  # noqa: F401

#: Seconds between readback polls while waiting for the knobs to reach their setpoints.
READBACK_POLL_S = 0.05
#: Default tolerance: relative part (of each knob's range) and absolute floor (knob units).
TOLERANCE_REL = 1e-6
TOLERANCE_ABS = 1e-9


class EpicsMachine(ObjectiveReader, GuardedMachine):
    r"""Knobs and objective of a machine controlled over EPICS Channel Access.

    See the module docstring for the exact set / read / get behaviour and the default tolerance.

    Args:
        knob_names: ``d`` knob names (e.g. ``"01G-QSS4"``).
        bounds: ``2 x d`` allowed knob range (setpoint units).
        objective_pv: PV of the objective (e.g. ``"SPEAR:BeamLossRate"``).
        setpoint_pvs: ``d`` setpoint PV names (default: ``knob + setpoint_suffix``).
        readback_pvs: ``d`` readback PV names (default: ``knob + readback_suffix``).
        setpoint_suffix: default ``":CurrSetpt"``.
        readback_suffix: default ``":Curr1"``.
        settle_time: seconds to wait after the puts before the readbacks are checked (>= 0).
        tolerance: allowed :math:`|x_\mathrm{rb} - x|`: a scalar or ``d`` tensor in knob units;
            ``None``: :math:`10^{-6}(h - \ell) + 10^{-9}` per knob.
        n_average: readings averaged per :meth:`read` (>= 1).
        average_interval: seconds between those readings (>= 0).
        timeout: seconds allowed for connecting, for each group of CA reads or puts, and for the
            readbacks to arrive after ``settle_time``.
        max_step: per-knob maximum change per :meth:`set` (scalar fraction of the half-range or
            ``d`` absolute tensor, see :func:`~pigp_torch.machine.base.max_step_tensor`).
        read_retries: extra attempts for an invalid objective reading (>= 0).
        context: a ``caproto.threading.client.Context`` to share (not closed by :meth:`close`).
        retry_interval: seconds between the attempts of one reading (>= 0).
        stale_timeout: seconds a reading may wait for the objective PV's timestamp to advance
            (> 0; default 10).
        stale_poll: seconds between reads of a stale objective PV (> 0; default 0.05).
        check_control_limits: refuse bounds outside the setpoint PVs' control limits (default
            true).
        observable_pvs: ``{name: PV}`` of what each reading also measures (e.g. a screen's
            beam numbers), read once after the objective (default ``None``: none).
        observable_units: ``{name: unit}`` for every name of ``observable_pvs`` (default:
            ``""`` each).
        refuse_severity: ``"INVALID"`` (default) or ``"MAJOR"``: the alarm severity from
            which a reading is not valid (:class:`~pigp_torch.machine.errors.SeverityError`).

    Raises:
        ValueError: inconsistent names/bounds/options, readbacks outside the bounds at start, or
            bounds outside the IOC's control limits.
        MachineError: some PVs did not connect within ``timeout`` (all are listed).

    Attributes:
        n_reads: valid objective readings taken; n_invalid_readings: those retried or failed.
        control_limits: ``2 x d`` control limits of the setpoint PVs (NaN where none).
        objective_limits: ``(lower, upper)`` of the objective PV (``None``: it has none).
        last_reading: ``{"stamps": [...], "values": [...], "stale_polls": n}`` of the last
            :meth:`read` (CA timestamps of its readings, UNIX seconds; the readings averaged;
            reads of a value not yet updated).
        observable_names, observable_units: the observables' names and units (``None``
            without observable PVs); last_observables: ``m`` values of the last :meth:`read`.

    Not thread-safe: use one machine from one thread. Use as a context manager (or call
    :meth:`close`) to release the CA connections.
    """

    #: The client adapter (connect, read_many, read_timed, control_limits, write_many, close,
    #: disconnections); :class:`~pigp_torch.machine.pva.PvaMachine` swaps in pvAccess.
    _adapter_class = CaprotoAdapter

    def __init__(
        self,
        knob_names,
        bounds,
        objective_pv: str,
        *,
        setpoint_pvs=None,
        readback_pvs=None,
        setpoint_suffix: str = ":CurrSetpt",
        readback_suffix: str = ":Curr1",
        settle_time: float = 0.5,
        tolerance=None,
        n_average: int = 1,
        average_interval: float = 0.0,
        timeout: float = 2.0,
        max_step=None,
        read_retries: int = 2,
        context=None,
        retry_interval: float = 0.1,
        stale_timeout: float = 10.0,
        stale_poll: float = 0.05,
        check_control_limits: bool = True,
        observable_pvs: dict[str, str] | None = None,
        observable_units: dict[str, str] | None = None,
        refuse_severity: str = "INVALID",
    ) -> None:
        # Everything that can be checked without the control system is checked first.
        names = [str(n) for n in knob_names]
        bounds = check_bounds(bounds)
        if bounds.shape[1] != len(names):
            raise ValueError(f"{len(names)} knob names for {bounds.shape[1]} knobs")
        if len(set(names)) != len(names):
            raise ValueError("knob names must be unique")
        max_step_tensor(max_step, bounds)
        tolerance = self._tolerance(tolerance, bounds)
        self.setpoint_pvs = self._pv_list(setpoint_pvs, names, setpoint_suffix, "setpoint_pvs")
        self.readback_pvs = self._pv_list(readback_pvs, names, readback_suffix, "readback_pvs")
        if not isinstance(objective_pv, str) or not objective_pv:
            raise ValueError(f"objective_pv must be a non-empty PV name, got {objective_pv!r}")
        self.objective_pv = objective_pv
        self._observables(observable_pvs, observable_units)
        self.settle_time = self._nonneg(settle_time, "settle_time")
        self.average_interval = self._nonneg(average_interval, "average_interval")
        self.retry_interval = self._nonneg(retry_interval, "retry_interval")
        self.timeout = float(timeout)
        if not (0.0 < self.timeout < math.inf):
            raise ValueError(f"timeout must be positive and finite, got {timeout}")
        if int(n_average) != n_average or n_average < 1:
            raise ValueError(f"n_average must be an integer >= 1, got {n_average}")
        if int(read_retries) != read_retries or read_retries < 0:
            raise ValueError(f"read_retries must be an integer >= 0, got {read_retries}")
        self.n_average = int(n_average)
        self.read_retries = int(read_retries)
        self.stale_timeout = float(stale_timeout)
        self.stale_poll = float(stale_poll)
        for key, value in (("stale_timeout", self.stale_timeout), ("stale_poll", self.stale_poll)):
            if not (0.0 < value < math.inf):
                raise ValueError(f"{key} must be positive and finite, got {value}")
        self.refuse_severity = self._severity_level(refuse_severity)
        self.n_reads = 0
        self.n_invalid_readings = 0
        self.last_reading: dict | None = None
        self._last_stamp: float | None = None
        self._closed = False

        self._ca = self._adapter_class(context, timeout=self.timeout)
        try:
            missing = self._ca.connect(
                [*self.setpoint_pvs, *self.readback_pvs, objective_pv, *self.observable_pvs],
                self.timeout,
            )
            if missing:
                raise MachineError(
                    f"{len(missing)} PV(s) did not connect within {self.timeout:g} s: "
                    + ", ".join(missing)
                    + " (check the PV names and where Channel Access searches: "
                    "EPICS_CA_ADDR_LIST and EPICS_CA_AUTO_ADDR_LIST; for pigp serve-sim on this "
                    "host: export EPICS_CA_ADDR_LIST=127.0.0.1:<its --port> "
                    "EPICS_CA_AUTO_ADDR_LIST=NO)"
                )
            limits = self._ca.control_limits(self.setpoint_pvs, self.timeout)
            self.control_limits = torch.tensor(
                [[lo for lo, _, _ in limits], [hi for _, hi, _ in limits]], dtype=DTYPE
            )
            if check_control_limits:
                refuse_outside_control_limits(names, bounds, limits)
            ((obj_lo, obj_hi, obj_src),) = self._ca.control_limits([objective_pv], self.timeout)
            self.objective_limits = None if obj_src == "none" else (obj_lo, obj_hi)
            x_now = torch.tensor(self._read_knobs(), dtype=DTYPE)
            try:
                check_setting(x_now, bounds)
            except ValueError as err:
                raise ValueError(f"the knobs' current readbacks are not allowed: {err}") from err
            sp_now = self._ca.read_many(self.setpoint_pvs, self.timeout)
            try:
                check_setting(torch.tensor(sp_now, dtype=DTYPE), bounds)
            except ValueError as err:
                raise ValueError(f"the knobs' current setpoints are not allowed: {err}") from err
            super().__init__(bounds, names, max_step=max_step, x_init=x_now)
            self._x = torch.tensor(sp_now, dtype=DTYPE)
            self._acknowledged = [float(v) for v in sp_now]
            self.tolerance = tolerance
        except BaseException:
            self._ca.close()
            raise

    # ------------------------------------------------------------------ validation helpers
    @staticmethod
    def _pv_list(pvs, names: list[str], suffix: str, what: str) -> list[str]:
        if pvs is None:
            return [f"{n}{suffix}" for n in names]
        pvs = [str(p) for p in pvs]
        if len(pvs) != len(names):
            raise ValueError(f"{what}: {len(pvs)} PV names for {len(names)} knobs")
        if len(set(pvs)) != len(pvs):
            raise ValueError(f"{what} must be unique")
        return pvs

    def _observables(self, pvs: dict[str, str] | None, units: dict[str, str] | None) -> None:
        pvs = dict(pvs or {})
        if units is not None and set(units) != set(pvs):
            raise ValueError(f"observable_units {sorted(units)} must name every observable "
                             f"{sorted(pvs)}")  # fmt: skip
        if any(not isinstance(pv, str) or not pv for pv in pvs.values()):
            raise ValueError(f"observable_pvs must map names to non-empty PV names, got {pvs}")
        self.observable_pvs = list(pvs.values())
        self.observable_names = tuple(pvs) or None
        self.observable_units = tuple(str((units or {}).get(n, "")) for n in pvs) or None
        self.last_observables = None

    @staticmethod
    def _nonneg(value, name: str) -> float:
        value = float(value)
        if not (0.0 <= value < math.inf):
            raise ValueError(f"{name} must be finite and >= 0, got {value}")
        return value

    @staticmethod
    def _tolerance(tolerance, bounds: torch.Tensor) -> torch.Tensor:
        width = bounds[1] - bounds[0]
        d = width.numel()
        if tolerance is None:
            return TOLERANCE_REL * width + TOLERANCE_ABS
        tol = torch.as_tensor(tolerance, dtype=DTYPE)
        if tol.dim() == 0:
            tol = tol.expand(d).clone()
        if tol.shape != (d,):
            raise ValueError(f"tolerance must be a scalar or ({d},); got {tuple(tol.shape)}")
        if not torch.isfinite(tol).all() or (tol < 0).any():
            raise ValueError("tolerance entries must be finite and >= 0")
        return tol

    def _check_open(self) -> None:
        if self._closed:
            raise MachineError("the EpicsMachine is closed")

    # ------------------------------------------------------------------ CA operations
    def get(self) -> torch.Tensor:
        """The knob readbacks read over CA now (``d`` float64).

        Raises:
            MachineError: a readback could not be read within ``timeout`` or is not finite.
        """
        self._check_open()
        return torch.tensor(self._read_knobs(), dtype=DTYPE)

    def setpoints(self) -> torch.Tensor:
        """The setpoint PVs read over CA now (``d`` float64).

        Raises:
            MachineError: a setpoint could not be read within ``timeout``.
        """
        self._check_open()
        return torch.tensor(self._ca.read_many(self.setpoint_pvs, self.timeout), dtype=DTYPE)

    @property
    def last_acknowledged(self) -> torch.Tensor:
        r"""The setpoints the IOC last confirmed, per knob (``d`` float64): the setpoint PVs read
        at connection or before the last set, updated by every put completion of ours. After a
        failed set (a put never completed, the IOC died) it is what the IOC really received, not
        what was intended."""
        return torch.tensor(self._acknowledged, dtype=DTYPE)

    @property
    def disconnections(self) -> int:
        """Channel disconnections seen since the machine connected (all its PVs)."""
        return self._ca.disconnections if self._ca is not None else 0

    def set(self, x) -> None:
        """Check ``x`` against the bounds and ``max_step`` (from the setpoint PVs read now),
        then apply it.

        Raises:
            ValueError: the setting is refused (nothing written).
            MachineError: the setpoints could not be read, or the puts were not confirmed
                within ``timeout``.
            ReadbackError: a readback did not reach its setpoint within the tolerance in time
                (the puts themselves were completed: see :attr:`last_acknowledged`).
        """
        self._check_open()
        # max_step is measured from the setpoints the IOC holds now (never from readbacks)
        sp = self.setpoints()
        self._x = sp
        self._acknowledged = sp.tolist()
        super().set(x)

    def _apply(self, x: torch.Tensor) -> None:
        """Write the setpoints that change (those equal to the setpoints read just before are
        not put again: a knob the IOC would now refuse, e.g. outside narrowed control limits,
        does not block the others), wait ``settle_time``, poll the readbacks until they match."""
        target = x.tolist()
        held = self._x.tolist()
        changed = [i for i in range(len(target)) if target[i] != held[i]]

        def on_ack(k: int) -> None:  # a put completion arrived: the IOC holds that target
            self._acknowledged[changed[k]] = target[changed[k]]

        if changed:
            self._ca.write_many(
                [self.setpoint_pvs[i] for i in changed], [target[i] for i in changed],
                self.timeout, on_ack=on_ack,
            )  # fmt: skip
        if self.settle_time > 0:
            time.sleep(self.settle_time)
        deadline = time.monotonic() + self.timeout
        while True:  # a readback of a refused severity reads NaN: not there yet
            rb = torch.tensor(self._read_knobs(refuse=False), dtype=DTYPE)
            off = ((rb - x).abs() > self.tolerance).nonzero().flatten().tolist()
            if not off:
                return
            if time.monotonic() >= deadline:
                detail = ", ".join(
                    f"{self.knob_names[i]}: setpoint {target[i]:.9g}, readback "
                    + (f"{float(rb[i]):.9g}" if rb[i] == rb[i] else "of a refused severity")
                    + f" (tolerance {float(self.tolerance[i]):.3g})"
                    for i in off
                )
                raise ReadbackError(
                    f"{len(off)} knob(s) did not reach their setpoints within "
                    f"{self.settle_time:g} s + {self.timeout:g} s: {detail}"
                )
            time.sleep(min(READBACK_POLL_S, max(0.0, deadline - time.monotonic())))

    # ------------------------------------------------------------------ lifetime
    def close(self) -> None:
        """Release the CA connections (idempotent); later calls raise :class:`MachineError`."""
        if not self._closed:
            self._closed = True
            self._ca.close()

    def __enter__(self) -> EpicsMachine:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        state = "closed" if self._closed else "open"
        return (
            f"EpicsMachine({self.dim} knobs, objective {self.objective_pv!r}, "
            f"settle {self.settle_time:g} s, {state})"
        )
