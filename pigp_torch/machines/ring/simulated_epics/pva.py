r"""The simulated ring served over EPICS 7 pvAccess (a ``p4p`` server on 127.0.0.1).

The pvAccess twin of :mod:`pigp_torch.machines.ring.simulated_epics.ioc`, for tests and demos of
:class:`~pigp_torch.machine.pva.PvaMachine`: the same PV names, all ``NTScalar`` doubles (the
switches too):

========================  ==========  ========================================================
PV                        access      meaning
========================  ==========  ========================================================
``<knob>:CurrSetpt``      read/write  knob setpoint; ``control`` and ``display`` limits are the
                                      knob bounds, a put outside them is refused (an error)
``<knob>:Curr1``          read only   readback: follows the setpoint after ``ReadbackDelay``
``P BeamLossRate``        read only   loss rate at the readbacks + noise, posted every
                                      ``update_period`` s with the time of the refresh
``P Sim:ReadbackDelay``   read/write  fault injection: seconds before readbacks follow (>= 0)
``P Sim:Frozen``          read/write  fault injection (tests): 1 stops the refreshes
``P Sim:Reboot``          read/write  fault injection (tests): a put of 1 "reboots the IOC":
                                      every setpoint and readback back at its power-on value
``P Sim:AlarmSeverity``   read/write  fault injection: the ``alarm.severity`` the two switches
                                      below post (0 NO_ALARM .. 3 INVALID; default 3)
``P Sim:AlarmPosts``      read/write  fault injection: the next N loss-rate refreshes are
                                      posted with that severity (-1: every one until reset);
                                      the values so posted are kept in ``alarm_values``
``P Sim:AlarmKnob``       read/write  fault injection: ``k`` >= 1 posts the readback of knob
                                      ``k`` with that severity (until reset to 0)
========================  ==========  ========================================================

(pvAccess serves gets from the posted value, so the per-read switches of the CA IOC,
``NanReadings`` and ``RebootOnRead``, have no twin here and ``AlarmReadings`` is
``AlarmPosts``; a test triggers ``Sim:Reboot`` at the moment it needs.) The server binds to
127.0.0.1 only and sends its beacons there. Needs the optional extra ``pva`` (``p4p``).
"""

from __future__ import annotations

import contextlib
import math
import threading
import time
from collections.abc import Iterator

import torch

from pigp_torch._utils import DTYPE, check_bounds
from pigp_torch.machine.base import check_setting
from pigp_torch.machines.ring.simulated_epics import (
    ALARM_KNOB_SUFFIX,
    ALARM_SEVERITY_SUFFIX,
    DEFAULT_PREFIX,
    FROZEN_SUFFIX,
    LOOPBACK,
    LOSS_RATE_SUFFIX,
    READBACK_DELAY_SUFFIX,
    READBACK_SUFFIX,
    SETPOINT_SUFFIX,
)

REBOOT_SUFFIX = "Sim:Reboot"
ALARM_POSTS_SUFFIX = "Sim:AlarmPosts"


def free_udp_tcp_ports(n: int = 2, attempts: int = 50) -> list[int]:
    """``n`` distinct ports free for TCP and UDP on 127.0.0.1 (:func:`~.
    free_ports`)."""
    from pigp_torch.machines.ring.simulated_epics import free_ports

    return free_ports(n, attempts)


def server_conf(server_port: int, broadcast_port: int) -> dict[str, str]:
    """p4p server configuration: 127.0.0.1 only, on these ports, beacons to 127.0.0.1."""
    return {
        "EPICS_PVAS_INTF_ADDR_LIST": LOOPBACK,
        "EPICS_PVAS_SERVER_PORT": str(int(server_port)),
        "EPICS_PVAS_BROADCAST_PORT": str(int(broadcast_port)),
        "EPICS_PVAS_AUTO_BEACON_ADDR_LIST": "NO",
        "EPICS_PVAS_BEACON_ADDR_LIST": LOOPBACK,
    }


def client_conf(server_port: int, broadcast_port: int) -> dict[str, str]:
    """p4p client configuration that searches only this server on 127.0.0.1."""
    return {
        "EPICS_PVA_ADDR_LIST": f"{LOOPBACK}:{int(broadcast_port)}",
        "EPICS_PVA_AUTO_ADDR_LIST": "NO",
        "EPICS_PVA_SERVER_PORT": str(int(server_port)),
        "EPICS_PVA_BROADCAST_PORT": str(int(broadcast_port)),
    }


class SimRingPVA:
    r"""The PVs of one simulated ring (see the module table), served by :meth:`serve`.

    Args:
        machine: a :class:`~pigp_torch.machine.SimulatedMachine` (its knob names and bounds are
            served).
        prefix: prefix of the loss-rate and switch PVs.
        update_period: seconds between loss-rate refreshes (> 0).
        x_init: initial (power-on) knobs (default zeros).
        readback_delay: initial ``Sim:ReadbackDelay`` (s, >= 0).
        units: engineering units of the knob PVs (the simulator's ``knob_units``).

    Raises:
        ValueError: bad arguments; ImportError: p4p is missing.
    """

    def __init__(
        self,
        machine,
        *,
        prefix: str = DEFAULT_PREFIX,
        update_period: float = 0.1,
        x_init=None,
        readback_delay: float = 0.0,
        units: str = "1/m",
    ) -> None:
        from p4p.nt import NTScalar
        from p4p.server.thread import SharedPV

        self.machine = machine
        self.knob_names = list(machine.knob_names)
        self.bounds = check_bounds(machine.bounds)
        d = len(self.knob_names)
        self.update_period = float(update_period)
        if not (0.0 < self.update_period < math.inf):
            raise ValueError(f"update_period must be positive and finite, got {update_period}")
        if not (0.0 <= float(readback_delay) < math.inf):
            raise ValueError(f"readback_delay must be finite and >= 0, got {readback_delay}")
        x0 = torch.zeros(d, dtype=DTYPE) if x_init is None else x_init
        self._power_on = check_setting(x0, self.bounds).tolist()
        self._x_readback = list(self._power_on)
        self._put_count = [0] * d
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._timers: list[threading.Timer] = []
        self.prefix = prefix

        def shared(initial: float, limits=None, units_=""):
            kind = NTScalar("d", control=True, display=True)
            value = {"value": float(initial), "display.units": units_}
            if limits is not None:
                lo, hi = limits
                value.update({"control.limitLow": lo, "control.limitHigh": hi})
                value.update({"display.limitLow": lo, "display.limitHigh": hi})
            return SharedPV(nt=kind, initial=value)

        self.pvs: dict[str, object] = {}
        self.setpoints, self.readbacks = [], []
        for i, name in enumerate(self.knob_names):
            lim = (float(self.bounds[0, i]), float(self.bounds[1, i]))
            sp = shared(self._power_on[i], lim, units)
            rb = shared(self._power_on[i], None, units)
            sp.put(self._setpoint_handler(i, lim))
            self.pvs[f"{name}{SETPOINT_SUFFIX}"] = sp
            self.pvs[f"{name}{READBACK_SUFFIX}"] = rb
            self.setpoints.append(sp)
            self.readbacks.append(rb)
        self.loss_rate = shared(self._reading(), None, "mA/min")
        self.readback_delay = shared(float(readback_delay), (0.0, 3600.0), "s")
        self.frozen = shared(0.0, (0.0, 1.0))
        self.reboot = shared(0.0, (0.0, 1.0))
        self.alarm_severity = shared(3.0, (0.0, 3.0))
        self.alarm_posts = shared(0.0, (-1.0, 1e6))
        self.alarm_knob = shared(0.0, (0.0, float(d)))
        #: Loss-rate values posted with an alarm (what a client must never take as a reading).
        self.alarm_values: list[float] = []
        for pv in (self.readback_delay, self.frozen, self.alarm_severity, self.alarm_posts):
            pv.put(self._switch_handler)
        self.alarm_knob.put(self._alarm_knob_handler)
        self.reboot.put(self._reboot_handler)
        self.pvs[f"{prefix}{LOSS_RATE_SUFFIX}"] = self.loss_rate
        self.pvs[f"{prefix}{READBACK_DELAY_SUFFIX}"] = self.readback_delay
        self.pvs[f"{prefix}{FROZEN_SUFFIX}"] = self.frozen
        self.pvs[f"{prefix}{REBOOT_SUFFIX}"] = self.reboot
        self.pvs[f"{prefix}{ALARM_SEVERITY_SUFFIX}"] = self.alarm_severity
        self.pvs[f"{prefix}{ALARM_POSTS_SUFFIX}"] = self.alarm_posts
        self.pvs[f"{prefix}{ALARM_KNOB_SUFFIX}"] = self.alarm_knob

    # ------------------------------------------------------------------ behaviour
    def _reading(self) -> float:
        with self._lock:
            x = torch.tensor(self._x_readback, dtype=DTYPE)
        self.machine.set(x)
        return float(self.machine.read())

    def _set_readback(self, i: int, value: float, count: int | None = None) -> None:
        with self._lock:
            if count is not None and count != self._put_count[i]:
                return  # a newer put won
            self._x_readback[i] = float(value)
        alarm = int(float(self.alarm_knob.current())) == i + 1
        self.readbacks[i].post(float(value), timestamp=time.time(), severity=self._severity(alarm))

    def _severity(self, on: bool) -> int:
        """``Sim:AlarmSeverity`` when ``on``, else 0 (NO_ALARM)."""
        return int(float(self.alarm_severity.current())) if on else 0

    def _alarm_knob_handler(self, pv, op) -> None:
        pv.post(float(op.value()), timestamp=time.time())
        op.done()
        for i, rb in enumerate(self.readbacks):
            with self._lock:
                value = self._x_readback[i]
            rb.post(value, timestamp=time.time(), severity=self._severity(op.value() == i + 1))

    def _setpoint_handler(self, i: int, limits: tuple[float, float]):
        def handler(pv, op):
            value = float(op.value())
            if not (limits[0] <= value <= limits[1]):
                op.done(error=f"{value} outside the control limits [{limits[0]}, {limits[1]}]")
                return
            pv.post(value, timestamp=time.time())
            with self._lock:
                self._put_count[i] += 1
                count = self._put_count[i]
            delay = float(self.readback_delay.current())
            if delay <= 0:
                self._set_readback(i, value)
            else:
                timer = threading.Timer(delay, self._set_readback, (i, value, count))
                timer.daemon = True
                self._timers.append(timer)
                timer.start()
            op.done()

        return handler

    @staticmethod
    def _switch_handler(pv, op) -> None:
        pv.post(float(op.value()), timestamp=time.time())
        op.done()

    def _reboot_handler(self, pv, op) -> None:
        if float(op.value()) >= 1:
            for i, value in enumerate(self._power_on):
                with self._lock:
                    self._put_count[i] += 1
                self.setpoints[i].post(value, timestamp=time.time())
                self._set_readback(i, value)
        op.done()

    def _refresh_loop(self) -> None:
        while not self._stop.is_set():
            t0 = time.monotonic()
            if not float(self.frozen.current()):
                value, posts = self._reading(), int(float(self.alarm_posts.current()))
                if posts > 0:
                    self.alarm_posts.post(float(posts - 1), timestamp=time.time())
                severity = self._severity(posts != 0)
                if severity > 0:
                    self.alarm_values.append(value)
                self.loss_rate.post(value, timestamp=time.time(), severity=severity)
            self._stop.wait(max(0.0, self.update_period - (time.monotonic() - t0)))

    # ------------------------------------------------------------------ serving
    @contextlib.contextmanager
    def serve(self, server_port: int | None = None, broadcast_port: int | None = None):
        """Serve the PVs on 127.0.0.1 for the block (a p4p server and a refresh thread); yields
        the client configuration (:func:`client_conf`)."""
        from p4p.server import Server

        if server_port is None or broadcast_port is None:
            server_port, broadcast_port = free_udp_tcp_ports(2)
        conf = server_conf(server_port, broadcast_port)
        thread = threading.Thread(target=self._refresh_loop, name="pva-sim-refresh", daemon=True)
        with Server(providers=[dict(self.pvs)], conf=conf, useenv=False):
            thread.start()
            try:
                yield client_conf(server_port, broadcast_port)
            finally:
                self._stop.set()
                thread.join(timeout=5.0)
                for timer in self._timers:
                    timer.cancel()

    @property
    def loss_rate_pv(self) -> str:
        return f"{self.prefix}{LOSS_RATE_SUFFIX}"

    def pv(self, suffix: str) -> str:
        """The full name of a ring-wide PV (``"Sim:Frozen"`` -> ``"SPEAR:Sim:Frozen"``)."""
        return f"{self.prefix}{suffix}"


@contextlib.contextmanager
def start_sim_pva(
    seed: int = 1,
    *,
    knobs="paper13",
    noise: float = 0.04,
    noise_seed: int = 0,
    prefix: str = DEFAULT_PREFIX,
    update_period: float = 0.1,
    x_init=None,
) -> Iterator[tuple[SimRingPVA, dict[str, str]]]:
    """Serve the SPEAR3 ring ``RingSpec(knobs=knobs).build(seed)`` over pvAccess on 127.0.0.1
    in this process (threads) for the block; yields ``(server, client_conf)``."""
    from pigp_torch.machine import SimulatedMachine
    from pigp_torch.machines.ring.spec import as_ring_spec

    sim = as_ring_spec(None, knobs=knobs).build(int(seed))
    machine = SimulatedMachine(sim, noise=noise, seed=noise_seed)
    ring = SimRingPVA(
        machine,
        prefix=prefix,
        update_period=update_period,
        x_init=x_init,
        units=getattr(sim, "knob_units", "1/m"),
    )
    with ring.serve() as conf:
        yield ring, conf
