r"""The PVs of the simulated ring's IOC: the caproto ``PVGroup`` and its class for given knobs.

The IOC makes the EPICS path testable end to end without a control room: the same
:class:`~pigp_torch.machine.epics.EpicsMachine` that would talk to SPEAR3 talks to this server over
real Channel Access on the loopback interface.

PVs served (``K`` knobs, prefix ``P``, default ``"SPEAR:"``):

========================  ==========  ========================================================
PV                        access      meaning
========================  ==========  ========================================================
``<knob>:CurrSetpt``      read/write  knob setpoint (winding current, A, by default); puts
                                      outside the knob bounds are refused (control limits)
``<knob>:Curr1``          read only   readback: follows the setpoint after ``ReadbackDelay``
``P BeamLossRate``        read only   loss rate at the *readbacks* + Gaussian noise (mA/min),
                                      refreshed every ``update_period`` seconds
``P Sim:ReadbackDelay``   read/write  fault injection: seconds before readbacks follow (>= 0)
``P Sim:NanReadings``     read/write  fault injection: the next N client reads of the loss
                                      rate return NaN (decremented on each read)
``P Sim:Frozen``          read/write  fault injection (tests): 1 stops the loss-rate refreshes
                                      (value and timestamp stay), 0 resumes them
``P Sim:RebootOnRead``    read/write  fault injection (tests): the N-th client read of the loss
                                      rate from now (decremented on each read) is answered,
                                      then the "IOC reboots": every setpoint and readback
                                      drops to its power-on value (the initial knobs)
``P Sim:GlitchReadings``  read/write  fault injection: the next N client reads of the loss
                                      rate return ``GlitchValue`` (decremented on each read),
                                      with a fresh timestamp, like a real glitch
``P Sim:GlitchValue``     read/write  the glitch's value (default 1e30 mA/min)
``P Sim:StuckKnob``       read/write  fault injection: ``k`` >= 1 freezes the readback of knob
                                      ``k`` (1-based, knob order) where it is: it no longer
                                      follows its setpoint (a stuck supply); 0 releases it
``P Sim:ReadbackOffset``  read/write  fault injection: every readback is its setpoint plus this
                                      offset (knob units; a calibration offset), clipped to
                                      the knob's bounds (a readback pushed past a bound reads
                                      the bound: the supply saturates, the IOC lives on)
``P Sim:NarrowKnob``      read/write  fault injection: the knob (1-based) whose control limits
                                      ``Sim:NarrowLimit`` narrows; 0 (default): every knob
``P Sim:NarrowLimit``     read/write  fault injection: ``L > 0`` narrows the control limits
                                      (DRVL/DRVH) of those knobs to :math:`[-L, L]` within
                                      their bounds, so the IOC refuses a put outside; 0 puts
                                      the bounds back
``P Sim:StallPuts``       read/write  fault injection: for the next ``t`` seconds every
                                      setpoint put is held unanswered until the stall ends,
                                      then refused (nothing applied): an IOC restarting
``P Sim:AlarmSeverity``   read/write  fault injection: the alarm severity the two switches
                                      below serve (0 NO_ALARM .. 3 INVALID; default 3)
``P Sim:AlarmReadings``   read/write  fault injection: the next N client reads of the loss
                                      rate carry that severity (decremented on each read, a
                                      fresh timestamp); -1: every read and refresh until reset
``P Sim:AlarmKnob``       read/write  fault injection: ``k`` >= 1 serves the readback of knob
                                      ``k`` with that severity (always, until reset to 0)
========================  ==========  ========================================================

**Put log.** With ``put_log`` (``pigp serve-sim --put-log FILE``) every put the IOC accepts on
a setpoint (after the control limits) is appended to that file as a JSON line
``{"pv", "knob", "value", "previous", "time"}`` — ``previous`` is the setpoint before the put,
so ``|value - previous|`` is the step the IOC was asked for — and an IOC reboot as
``{"reboot": true, "time"}``. Tests read it (:meth:`SimIOCProcess.puts
<.ioc_process.SimIOCProcess.puts>`) to check what the IOC received,
independently of the client.

The loss-rate PV has display limits ``LOPR``/``HOPR`` = ``LOSS_RATE_LIMITS`` ([0, 100] mA/min),
the plausible range a client may take as the objective's physical range.

The loss rate's CA timestamp is the time of its last refresh (a client read does not renew
it), so a client can tell a fresh reading from a repeated one.

The physics is :class:`~pigp_torch.machine.SimulatedMachine` around a
:class:`~..ring.RingCoupling` ring: at every refresh the machine is set to the
readbacks and one noisy reading :math:`y = f(x_\mathrm{rb}) + \epsilon`,
:math:`\epsilon \sim \mathcal N(0, \sigma_n^2)` (seeded, default :math:`\sigma_n` = 0.04 mA/min),
is published. Between refreshes a read returns the last published value, as on a real monitor
PV; a client that averages readings should space them by at least ``update_period``.

Knob values are served in the simulator's control units (amps of the SPEAR3 skew windings; the
``EGU`` field of each knob PV says so), as on the real machine.

Safety: the server binds to 127.0.0.1 only (``EPICS_CAS_INTF_ADDR_LIST``) and sends its beacons
to 127.0.0.1 only. :func:`start_sim_ioc` runs it in a subprocess on a free port for tests and
demos; ``pigp serve-sim`` runs it in the foreground.
"""

from __future__ import annotations

import asyncio
import json
import math
import time
from pathlib import Path

import torch
from caproto import AlarmSeverity, AlarmStatus
from caproto.server import PVGroup

from pigp_torch._utils import DTYPE


# ----------------------------------------------------------------------------- the PV group
class SimRingIOC(PVGroup):
    r"""Behaviour of the simulated ring IOC; its PVs are added by :func:`sim_ioc_class`.

    Do not instantiate directly: use :func:`make_sim_ioc` (or :func:`sim_ioc_class`), which builds
    a subclass with one setpoint/readback pvproperty pair per knob (the knob names are only known
    at run time).

    The initial knob values and switch settings are the pvproperty defaults chosen in
    :func:`sim_ioc_class`.

    Args:
        machine: the :class:`~pigp_torch.machine.SimulatedMachine` that produces the readings.
        update_period: seconds between loss-rate refreshes (> 0).
        put_log: file to append every accepted setpoint put to (JSON lines), or ``None``.
        **kwargs: passed to :class:`caproto.server.PVGroup` (``prefix`` must stay ``""``: the
            names are complete already).
    """

    #: Filled in by :func:`sim_ioc_class`.
    knob_names: tuple[str, ...] = ()

    def __init__(
        self,
        *args,
        machine,
        update_period: float = 0.1,
        put_log=None,
        **kwargs,
    ) -> None:
        if not self.knob_names:
            raise ValueError("use sim_ioc_class()/make_sim_ioc(): this class serves no knobs")
        if list(machine.knob_names) != list(self.knob_names):
            raise ValueError("the machine's knob names differ from the IOC's")
        update_period = float(update_period)
        if not (0.0 < update_period < math.inf):
            raise ValueError(f"update_period must be positive and finite, got {update_period}")
        self.machine = machine
        self.update_period = update_period
        self.put_log = None if put_log is None else Path(put_log)
        super().__init__(*args, **kwargs)
        d = len(self.knob_names)
        self.setpoints = [getattr(self, f"setpoint_{i}") for i in range(d)]
        self.readbacks = [getattr(self, f"readback_{i}") for i in range(d)]
        self._x_readback = torch.tensor([rb.value for rb in self.readbacks], dtype=DTYPE)
        self._power_on = [float(sp.value) for sp in self.setpoints]
        self._last_reading = float("nan")
        self._refresh_stamp = time.time()
        self._served_nan = False
        self._served_glitch = False
        self._refresh()  # a valid first reading (this also checks the knobs against the bounds)
        self._put_count = [0] * d  # latest put per knob wins over older delayed readbacks
        self._tasks: set[asyncio.Task] = set()
        self._stall_until = 0.0  # monotonic time until which setpoint puts stall

    # ------------------------------------------------------------------ hooks
    def _log_put(self, entry: dict) -> None:
        """Append one entry to the put log (synchronous: a put is answered after it is logged)."""
        if self.put_log is None:
            return
        entry["time"] = time.time()
        with open(self.put_log, "a", encoding="utf-8") as f:
            f.write(json.dumps(entry) + "\n")

    async def _on_setpoint(self, i: int, value: float) -> None:
        """Setpoint ``i`` accepted (the control limits already passed): log the put, move its
        readback. During a stall (``Sim:StallPuts``) the put waits for its end, then fails."""
        stall = self._stall_until - time.monotonic()
        if stall > 0:
            await asyncio.sleep(stall)
            raise RuntimeError("setpoint put refused: the IOC was stalled (Sim:StallPuts)")
        self._log_put(
            {
                "pv": self.setpoints[i].pvspec.name,
                "knob": self.knob_names[i],
                "value": float(value),
                "previous": float(self.setpoints[i].value),
            }
        )
        self._put_count[i] += 1
        delay = float(self.readback_delay.value)
        if delay <= 0:
            await self._set_readback(i, value)
            return
        task = asyncio.get_running_loop().create_task(
            self._delayed_readback(i, value, self._put_count[i], delay)
        )
        self._tasks.add(task)  # keep a reference until it is done
        task.add_done_callback(self._tasks.discard)

    async def _delayed_readback(self, i: int, value: float, count: int, delay: float) -> None:
        await asyncio.sleep(delay)
        if self._put_count[i] == count:  # no newer put in the meantime
            await self._set_readback(i, value)

    async def _set_readback(self, i: int, value: float) -> None:
        """The readback of knob ``i`` follows setpoint ``value`` (plus ``ReadbackOffset``),
        unless ``StuckKnob`` names it."""
        if int(self.stuck_knob.value) == i + 1:
            return  # a stuck supply: the readback stays where it is
        await self._write_readback(i, float(value) + float(self.readback_offset.value))

    async def _write_readback(self, i: int, value: float) -> None:
        """Readback ``i`` reads ``value`` clipped to the knob's bounds (a supply pushed past its
        bound saturates there), so the simulated physics always sees an allowed setting."""
        lo, hi = (float(b) for b in self.machine.bounds[:, i])
        clipped = min(max(value, lo), hi)
        self._x_readback[i] = clipped
        alarm = self._alarm(int(self.alarm_knob.value) == i + 1)
        await self.readbacks[i].write(clipped, **alarm)

    def _alarm(self, on: bool) -> dict:
        """The alarm keywords of a write: ``Sim:AlarmSeverity`` (status READ) when ``on``, else
        none (NO_ALARM); ``verify_value`` off, as caproto's limit check would otherwise put
        the alarm of the record's own (absent) limits back over the one given."""
        severity = int(self.alarm_severity.value) if on else 0
        status = AlarmStatus.READ if severity else AlarmStatus.NO_ALARM
        return {"status": status, "severity": AlarmSeverity(severity), "verify_value": False}

    async def _on_alarm_knob(self, k: int) -> None:
        """A new ``Sim:AlarmKnob``: every readback written again with its alarm (knob ``k``'s
        with ``Sim:AlarmSeverity``, the others with none)."""
        for i, rb in enumerate(self.readbacks):
            await rb.write(float(rb.value), **self._alarm(k == i + 1))

    def _refresh(self) -> float:
        """One noisy reading of the simulated loss rate at the current readbacks."""
        self.machine.set(self._x_readback)
        self._last_reading = float(self.machine.read())
        self._refresh_stamp = time.time()
        return self._last_reading

    async def _refresh_loop(self, async_lib) -> None:
        """Publish a new loss-rate reading every ``update_period`` seconds (forever), except
        while ``Sim:Frozen`` is set."""
        sleep = async_lib.library.sleep
        while True:
            t0 = time.monotonic()
            if not int(self.frozen.value):
                value = self._refresh()
                alarm = self._alarm(int(self.alarm_readings.value) < 0)
                await self.loss_rate.write(value, timestamp=self._refresh_stamp, **alarm)
                self._served_nan = self._served_glitch = False
            await sleep(max(0.0, self.update_period - (time.monotonic() - t0)))

    async def _reboot(self) -> None:
        """Every setpoint and readback back at its power-on value (an IOC without autosave)."""
        self._log_put({"reboot": True})
        for i, value in enumerate(self._power_on):
            self._put_count[i] += 1
            await self.setpoints[i].write(value, verify_value=False)
            await self._set_readback(i, value)

    async def _on_read(self):
        """A client reads the loss rate: NaN while ``Sim:NanReadings`` > 0, else the last value
        with the timestamp of its refresh (``None``: the stored value is served unchanged)."""
        n_reboot = int(self.reboot_on_read.value)
        if n_reboot > 0:
            await self.reboot_on_read.write(n_reboot - 1)
            if n_reboot == 1:
                await self._reboot()
        value = None
        n = int(self.nan_readings.value)
        m = int(self.glitch_readings.value)
        if n > 0:
            await self.nan_readings.write(n - 1)
            self._served_nan = True
            value = float("nan")
        elif m > 0:  # served with the time of this read: it looks like a fresh reading
            await self.glitch_readings.write(m - 1)
            self._served_glitch = True
            value = float(self.glitch_value.value)
        k = int(self.alarm_readings.value)
        if k > 0:  # this read carries the alarm, with the time of this read
            await self.alarm_readings.write(k - 1)
            self._served_glitch = True  # the next read serves the last refresh again
            served = self._last_reading if value is None else value
            await self.loss_rate.write(served, timestamp=time.time(), **self._alarm(True))
            return None
        if value is not None:
            return value
        if self._served_nan or self._served_glitch:  # the last refresh, with its own timestamp
            self._served_nan = self._served_glitch = False
            await self.loss_rate.write(
                self._last_reading, timestamp=self._refresh_stamp, **self._alarm(k < 0)
            )
        return None

    async def _on_offset(self, offset: float) -> None:
        """A new ``ReadbackOffset``: every readback not stuck moves to its setpoint + offset."""
        for i, sp in enumerate(self.setpoints):
            if int(self.stuck_knob.value) != i + 1:
                await self._write_readback(i, float(sp.value) + offset)

    async def _on_narrow(self, limit: float) -> None:
        """A new ``Sim:NarrowLimit``: the control limits of ``Sim:NarrowKnob`` (0: every knob)
        become :math:`[-L, L]` within the bounds; ``L = 0``: the bounds again."""
        k = int(self.narrow_knob.value)
        for i, sp in enumerate(self.setpoints):
            if k not in (0, i + 1):
                continue
            lo, hi = (float(b) for b in self.machine.bounds[:, i])
            if limit > 0:
                lo, hi = max(lo, -limit), min(hi, limit)
            await sp.write_metadata(lower_ctrl_limit=lo, upper_ctrl_limit=hi)

    async def _on_stall(self, seconds: float) -> None:
        """A new ``Sim:StallPuts``: setpoint puts stall for ``seconds`` from now."""
        self._stall_until = time.monotonic() + max(0.0, seconds)

    # ------------------------------------------------------------------ names
    @property
    def loss_rate_pv(self) -> str:
        return self.loss_rate.pvspec.name

    @property
    def pv_names(self) -> list[str]:
        """Every PV served (setpoints, readbacks, loss rate, switches)."""
        return list(self.pvdb)
