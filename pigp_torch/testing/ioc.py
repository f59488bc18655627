r"""A simulated ring (SPEAR3 by default) served over EPICS Channel Access (a caproto IOC).

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
========================  ==========  ========================================================

The loss rate's CA timestamp is the time of its last refresh (a client read does not renew
it), so a client can tell a fresh reading from a repeated one.

The physics is :class:`~pigp_torch.machine.SimulatedMachine` around a
:class:`~pigp_torch.simulation.RingCoupling` ring: at every refresh the machine is set to the
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
import contextlib
import gc
import math
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import torch
from caproto import ChannelType
from caproto.server import PVGroup, pvproperty

from pigp_torch._utils import DTYPE, check_bounds
from pigp_torch.machine.base import check_setting
from pigp_torch.testing import (
    DEFAULT_PREFIX,
    FROZEN_SUFFIX,
    LOOPBACK,
    LOSS_RATE_SUFFIX,
    NAN_READINGS_SUFFIX,
    READBACK_DELAY_SUFFIX,
    READBACK_SUFFIX,
    REBOOT_ON_READ_SUFFIX,
    SETPOINT_SUFFIX,
    add_ioc_arguments,
    free_ports,
)

#: Printed by the IOC once its sockets are bound; :func:`start_sim_ioc` waits for it.
READY_MESSAGE = "pigp sim IOC ready"


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
        super().__init__(*args, **kwargs)
        d = len(self.knob_names)
        self.setpoints = [getattr(self, f"setpoint_{i}") for i in range(d)]
        self.readbacks = [getattr(self, f"readback_{i}") for i in range(d)]
        self._x_readback = torch.tensor([rb.value for rb in self.readbacks], dtype=DTYPE)
        self._power_on = [float(sp.value) for sp in self.setpoints]
        self._last_reading = float("nan")
        self._refresh_stamp = time.time()
        self._served_nan = False
        self._refresh()  # a valid first reading (this also checks the knobs against the bounds)
        self._put_count = [0] * d  # latest put per knob wins over older delayed readbacks
        self._tasks: set[asyncio.Task] = set()

    # ------------------------------------------------------------------ hooks
    async def _on_setpoint(self, i: int, value: float) -> None:
        """Setpoint ``i`` accepted (the control limits already passed): move its readback."""
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
        self._x_readback[i] = float(value)
        await self.readbacks[i].write(float(value))

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
                await self.loss_rate.write(value, timestamp=self._refresh_stamp)
                self._served_nan = False
            await sleep(max(0.0, self.update_period - (time.monotonic() - t0)))

    async def _reboot(self) -> None:
        """Every setpoint and readback back at its power-on value (an IOC without autosave)."""
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
        n = int(self.nan_readings.value)
        if n > 0:
            await self.nan_readings.write(n - 1)
            self._served_nan = True
            return float("nan")
        if self._served_nan:  # put the last refresh back, with its own timestamp
            self._served_nan = False
            await self.loss_rate.write(self._last_reading, timestamp=self._refresh_stamp)
        return None

    # ------------------------------------------------------------------ names
    @property
    def loss_rate_pv(self) -> str:
        return self.loss_rate.pvspec.name

    @property
    def pv_names(self) -> list[str]:
        """Every PV served (setpoints, readbacks, loss rate, switches)."""
        return list(self.pvdb)


def sim_ioc_class(
    knob_names,
    bounds,
    *,
    prefix: str = DEFAULT_PREFIX,
    setpoint_suffix: str = SETPOINT_SUFFIX,
    readback_suffix: str = READBACK_SUFFIX,
    x_init=None,
    readback_delay: float = 0.0,
    nan_readings: int = 0,
    units: str = "A",
) -> type[SimRingIOC]:
    r"""A :class:`SimRingIOC` subclass with the PVs of ``knob_names`` (see the module table).

    The pvproperties are created here because caproto collects them at class creation and the
    knob names are data. Each setpoint has control limits :math:`[\ell_i, h_i]` from ``bounds``,
    so caproto itself refuses a put outside them (the put fails with an error status; the
    setpoint and readback are unchanged).

    Args:
        knob_names: ``K`` knob names (PV name stems, e.g. ``"01G-QSS4"``).
        bounds: ``2 x K`` knob bounds.
        prefix: prefix of the loss-rate and switch PVs.
        setpoint_suffix, readback_suffix: appended to each knob name.
        x_init: ``K`` initial setpoints and readbacks (default zeros: skews off).
        readback_delay: initial value of the ``Sim:ReadbackDelay`` switch (s, >= 0).
        nan_readings: initial value of the ``Sim:NanReadings`` switch (>= 0).
        units: engineering units of the knob PVs (default ``"A"``).
    """
    names = [str(n) for n in knob_names]
    bounds = check_bounds(bounds)
    if len(names) != bounds.shape[1]:
        raise ValueError(f"{len(names)} knob names for {bounds.shape[1]} knobs")
    if len(set(names)) != len(names):
        raise ValueError("knob names must be unique")
    x0 = torch.zeros(len(names), dtype=DTYPE) if x_init is None else x_init
    x0 = check_setting(x0, bounds).tolist()
    if not (0.0 <= float(readback_delay) < math.inf):
        raise ValueError(f"readback_delay must be finite and >= 0, got {readback_delay}")
    if int(nan_readings) < 0:
        raise ValueError(f"nan_readings must be >= 0, got {nan_readings}")
    attrs: dict = {"knob_names": tuple(names), "__module__": __name__}
    for i, name in enumerate(names):
        lo, hi = float(bounds[0, i]), float(bounds[1, i])
        setpoint = pvproperty(
            value=x0[i],
            name=f"{name}{setpoint_suffix}",
            dtype=ChannelType.DOUBLE,
            lower_ctrl_limit=lo,
            upper_ctrl_limit=hi,
            precision=6,
            units=str(units),
            doc=f"setpoint of {name} ({units}), limits [{lo}, {hi}]",
        )

        async def put(group, instance, value, _i=i):
            await group._on_setpoint(_i, value)

        setpoint.putter(put)
        attrs[f"setpoint_{i}"] = setpoint
        attrs[f"readback_{i}"] = pvproperty(
            value=x0[i],
            name=f"{name}{readback_suffix}",
            dtype=ChannelType.DOUBLE,
            read_only=True,
            precision=6,
            units=str(units),
            doc=f"readback of {name} ({units})",
        )

    loss_rate = pvproperty(
        value=float("nan"),
        name=f"{prefix}{LOSS_RATE_SUFFIX}",
        dtype=ChannelType.DOUBLE,
        read_only=True,
        precision=4,
        units="mA/min",
        doc="simulated loss rate at the readbacks plus Gaussian noise (mA/min)",
    )

    async def start_refresh(group, instance, async_lib):
        await group._refresh_loop(async_lib)

    async def get_loss_rate(group, instance):
        return await group._on_read()

    loss_rate.startup(start_refresh)
    loss_rate.getter(get_loss_rate)
    attrs["loss_rate"] = loss_rate
    attrs["readback_delay"] = pvproperty(
        value=float(readback_delay),
        name=f"{prefix}{READBACK_DELAY_SUFFIX}",
        dtype=ChannelType.DOUBLE,
        lower_ctrl_limit=0.0,
        upper_ctrl_limit=3600.0,
        units="s",
        doc="fault injection: seconds before a readback follows its setpoint",
    )
    switches = (  # (attribute, suffix, initial value, upper limit, meaning)
        ("nan_readings", NAN_READINGS_SUFFIX, int(nan_readings), 1_000_000,
         "fault injection: the next N reads of the loss rate return NaN"),
        ("frozen", FROZEN_SUFFIX, 0, 1,
         "fault injection (tests): 1 stops the loss-rate refreshes"),
        ("reboot_on_read", REBOOT_ON_READ_SUFFIX, 0, 1_000_000,
         "fault injection (tests): reboot (knobs to power-on values) at the N-th read"),
    )  # fmt: skip
    for attr, suffix, value, upper, doc in switches:
        attrs[attr] = pvproperty(
            value=value,
            name=f"{prefix}{suffix}",
            dtype=ChannelType.LONG,
            lower_ctrl_limit=0,
            upper_ctrl_limit=upper,
            doc=doc,
        )
    return type("SimRingIOCWithKnobs", (SimRingIOC,), attrs)


def make_sim_ioc(
    seed: int = 1,
    *,
    knobs=None,
    ring=None,
    noise: float = 0.04,
    noise_seed: int = 0,
    prefix: str = DEFAULT_PREFIX,
    update_period: float = 0.1,
    readback_delay: float = 0.0,
    nan_readings: int = 0,
    x_init=None,
) -> SimRingIOC:
    """The IOC of machine ``ring.build(seed)`` (not yet serving).

    Args:
        seed: error seed of the simulated ring.
        knobs: knob set or names (overrides ``ring``'s).
        ring: a :class:`~pigp_torch.simulation.spec.RingSpec` (default: SPEAR3, 13 knobs, A).
        noise: loss-rate noise standard deviation (mA/min); ``noise_seed`` seeds it.
        prefix: prefix of the loss-rate and switch PVs.
        update_period: see :class:`SimRingIOC`.
        readback_delay, nan_readings, x_init: see :func:`sim_ioc_class`.
    """
    from pigp_torch.machine import SimulatedMachine
    from pigp_torch.simulation.spec import as_ring_spec

    # cheap checks before the ring is built (seconds)
    if not (0.0 <= float(noise) < math.inf):
        raise ValueError(f"noise must be finite and >= 0, got {noise}")
    if not (0.0 < float(update_period) < math.inf):
        raise ValueError(f"update_period must be positive and finite, got {update_period}")
    if isinstance(knobs, str) and "," in knobs:
        knobs = tuple(knobs.split(","))
    elif knobs is not None and not isinstance(knobs, str):
        knobs = tuple(knobs)
    sim = as_ring_spec(ring, knobs=knobs).build(int(seed))
    machine = SimulatedMachine(sim, noise=noise, seed=noise_seed)
    cls = sim_ioc_class(
        sim.knob_names,
        sim.bounds,
        prefix=prefix,
        x_init=x_init,
        readback_delay=readback_delay,
        nan_readings=nan_readings,
        units=sim.knob_units,
    )
    return cls(prefix="", machine=machine, update_period=update_period)


# ----------------------------------------------------------------------------- environment
def server_environment(port: int) -> dict[str, str]:
    """EPICS variables that keep a server on 127.0.0.1 at ``port`` (searches, TCP, beacons).

    Beacons go to 127.0.0.1 at ``port`` too, i.e. to the server's own search socket, which
    ignores them: they never leave the host, and no "connection refused" error is logged every
    beacon period when no CA repeater listens on 5065 (as on a test machine).
    """
    return {
        "EPICS_CAS_INTF_ADDR_LIST": LOOPBACK,
        "EPICS_CA_SERVER_PORT": str(int(port)),
        "EPICS_CAS_SERVER_PORT": str(int(port)),
        "EPICS_CAS_AUTO_BEACON_ADDR_LIST": "NO",
        "EPICS_CAS_BEACON_ADDR_LIST": LOOPBACK,
        "EPICS_CAS_BEACON_PORT": str(int(port)),
    }


def client_environment(port: int) -> dict[str, str]:
    """EPICS variables that make a client search only 127.0.0.1 at ``port``."""
    return {
        "EPICS_CA_ADDR_LIST": f"{LOOPBACK}:{int(port)}",
        "EPICS_CA_AUTO_ADDR_LIST": "NO",
        "EPICS_CA_SERVER_PORT": str(int(port)),
    }


@contextlib.contextmanager
def patched_environ(values: Mapping[str, str]) -> Iterator[None]:
    """Set ``os.environ`` entries for the block and restore the previous values after it.

    caproto clients read ``EPICS_CA_ADDR_LIST`` & co. from ``os.environ`` whenever they search,
    so this is how a test points its clients at one IOC.
    """
    old = {k: os.environ.get(k) for k in values}
    os.environ.update({k: str(v) for k, v in values.items()})
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def free_port(attempts: int = 50) -> int:
    """A port free for both TCP and UDP on 127.0.0.1 (chosen by the OS; bounded attempts)."""
    return free_ports(1, attempts)[0]


# ----------------------------------------------------------------------------- serving
def serve(ioc: SimRingIOC, port: int = 5064, *, log_pv_names: bool = True) -> None:
    """Run ``ioc`` in the foreground on 127.0.0.1:``port``; return after Ctrl-C or SIGTERM.

    Prints :data:`READY_MESSAGE` and (with ``log_pv_names``) the PV names once the server's
    sockets are bound. SIGTERM is handled as Ctrl-C (main thread only): ``asyncio.run`` cancels
    the server task, which closes its sockets and returns. SIGINT is given Python's default
    handler for the duration even where the parent ignored it (a background job started from a
    script), because the SIGTERM path goes through SIGINT.
    """
    import signal
    import threading

    from caproto.server import run

    os.environ.update(server_environment(port))  # read by caproto when the server starts

    async def announce(async_lib):
        print(f"{READY_MESSAGE} on {LOOPBACK}:{port}", flush=True)
        if log_pv_names:
            print("PVs served:\n  " + "\n  ".join(ioc.pv_names), flush=True)

    def on_sigterm(signum, frame):
        signal.raise_signal(signal.SIGINT)  # asyncio.run's own SIGINT handling: a clean stop

    in_main = threading.current_thread() is threading.main_thread()
    previous = previous_int = None
    if in_main:
        previous = signal.signal(signal.SIGTERM, on_sigterm)
        previous_int = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        run(ioc.pvdb, interfaces=[LOOPBACK], startup_hook=announce)  # returns on Ctrl-C
    finally:
        if in_main:
            signal.signal(signal.SIGTERM, previous)
            signal.signal(signal.SIGINT, previous_int)


def sim_ioc_from_args(args):
    """The IOC described by the options of :func:`pigp_torch.testing.add_ioc_arguments`."""
    from pigp_torch.ringargs import ring_spec_from_args

    return make_sim_ioc(
        args.seed,
        ring=ring_spec_from_args(args),
        noise=args.noise,
        noise_seed=args.noise_seed,
        prefix=args.prefix,
        update_period=args.update_period,
        readback_delay=args.readback_delay,
    )


def main(argv=None) -> int:
    """``python -m pigp_torch.testing.ioc``: serve the simulated ring (options as ``serve-sim``)."""
    import argparse

    torch.set_num_threads(1)
    p = argparse.ArgumentParser(
        prog="python -m pigp_torch.testing.ioc",
        description="Serve a simulated ring (SPEAR3 by default) over EPICS Channel Access on "
        "127.0.0.1.",
    )
    add_ioc_arguments(p)
    args = p.parse_args(argv)
    ioc = sim_ioc_from_args(args)
    # The ring's large, long-lived object graph need not be traversed by the garbage collector,
    # neither while serving nor at exit (that pass took ~2 s on a busy host).
    gc.freeze()
    serve(ioc, args.port)
    print("simulated IOC stopped", flush=True)
    return 0


# ----------------------------------------------------------------------------- subprocess helper
@dataclass
class SimIOCProcess:
    """A running simulated IOC subprocess (see :func:`start_sim_ioc`).

    Attributes:
        process: the ``subprocess.Popen`` handle.
        port: its Channel Access port on 127.0.0.1.
        knob_names: the knob names served.
        prefix: prefix of the loss-rate and switch PVs.
        log_path: file receiving the IOC's stdout and stderr.
    """

    process: subprocess.Popen
    port: int
    knob_names: list[str]
    prefix: str
    log_path: Path
    env: dict[str, str] = field(default_factory=dict)

    @property
    def loss_rate_pv(self) -> str:
        return f"{self.prefix}{LOSS_RATE_SUFFIX}"

    @property
    def nan_readings_pv(self) -> str:
        return f"{self.prefix}{NAN_READINGS_SUFFIX}"

    @property
    def readback_delay_pv(self) -> str:
        return f"{self.prefix}{READBACK_DELAY_SUFFIX}"

    @property
    def frozen_pv(self) -> str:
        return f"{self.prefix}{FROZEN_SUFFIX}"

    @property
    def reboot_on_read_pv(self) -> str:
        return f"{self.prefix}{REBOOT_ON_READ_SUFFIX}"

    @property
    def setpoint_pvs(self) -> list[str]:
        return [f"{n}{SETPOINT_SUFFIX}" for n in self.knob_names]

    @property
    def readback_pvs(self) -> list[str]:
        return [f"{n}{READBACK_SUFFIX}" for n in self.knob_names]

    @property
    def client_env(self) -> dict[str, str]:
        """EPICS client variables that reach this IOC (see :func:`client_environment`)."""
        return client_environment(self.port)

    def alive(self) -> bool:
        return self.process.poll() is None

    def log_tail(self, n_chars: int = 2000) -> str:
        try:
            return self.log_path.read_text(errors="replace")[-n_chars:]
        except OSError:
            return ""

    def stop(self, timeout: float = 5.0) -> None:
        """Terminate the IOC (SIGTERM, then SIGKILL after ``timeout`` s); idempotent."""
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(timeout)

    def kill(self, timeout: float = 5.0) -> None:
        """Kill the IOC at once (SIGKILL): a crash, for fault-injection tests."""
        if self.process.poll() is None:
            self.process.kill()
            self.process.wait(timeout)


def _wait_ready(handle: SimIOCProcess, timeout: float) -> None:
    """Wait for the IOC's ready line, then for its PVs to answer over CA (both bounded)."""
    deadline = time.monotonic() + timeout
    while READY_MESSAGE not in handle.log_tail(100_000):
        if not handle.alive():
            raise RuntimeError(
                f"simulated IOC exited with code {handle.process.returncode}:\n{handle.log_tail()}"
            )
        if time.monotonic() > deadline:
            raise TimeoutError(
                f"simulated IOC not ready after {timeout:.0f} s:\n{handle.log_tail()}"
            )
        time.sleep(0.05)
    from caproto.threading.client import Context

    ctx = Context()
    try:
        names = [handle.loss_rate_pv, handle.readback_pvs[-1]]
        pvs = ctx.get_pvs(*names, timeout=1.0)
        for pv in pvs:
            pv.wait_for_connection(timeout=max(0.5, deadline - time.monotonic()))
            pv.read(timeout=2.0)
    except Exception as err:
        raise TimeoutError(f"simulated IOC PVs did not answer over CA: {err!r}") from err
    finally:
        ctx.disconnect()


@contextlib.contextmanager
def start_sim_ioc(
    seed: int = 1,
    port: int | None = None,
    *,
    knobs="paper13",
    noise: float = 0.04,
    noise_seed: int = 0,
    prefix: str = DEFAULT_PREFIX,
    update_period: float = 0.1,
    readback_delay: float = 0.0,
    set_client_env: bool = True,
    startup_timeout: float = 90.0,
) -> Iterator[SimIOCProcess]:
    r"""Run the simulated IOC in a subprocess on 127.0.0.1 for the ``with`` block.

    Launches ``python -m pigp_torch.testing.ioc`` with the server bound to the loopback interface
    and ``port`` (default: a free one, so parallel runs do not collide), waits (at most
    ``startup_timeout`` s) for its ready line and for its PVs to answer over CA, and stops it
    (SIGTERM, then SIGKILL) when the block ends, also on errors.

    With ``set_client_env`` (default) the block runs with ``EPICS_CA_ADDR_LIST=127.0.0.1:port``,
    ``EPICS_CA_AUTO_ADDR_LIST=NO`` in ``os.environ`` (restored afterwards), so caproto clients of
    this process — e.g. :class:`~pigp_torch.machine.epics.EpicsMachine` — find this IOC and
    nothing else.

    Yields:
        a :class:`SimIOCProcess` (PV names, port, ``kill()`` for crash tests).

    Raises:
        RuntimeError: the IOC exited during start-up (its log is in the message).
        TimeoutError: it did not answer within ``startup_timeout``.
    """
    from pigp_torch.simulation.spear3 import knob_names_for

    names = knob_names_for(knobs)
    port = free_port() if port is None else int(port)
    cmd = [sys.executable, "-m", "pigp_torch.testing.ioc", "--seed", str(int(seed))]
    cmd += ["--knobs", knobs if isinstance(knobs, str) else ",".join(names)]
    cmd += ["--noise", repr(float(noise)), "--noise-seed", str(int(noise_seed))]
    cmd += ["--prefix", prefix, "--port", str(port)]
    cmd += ["--update-period", repr(float(update_period))]
    cmd += ["--readback-delay", repr(float(readback_delay))]
    env = dict(os.environ)
    env.update(server_environment(port))
    env.update(OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
    env["PYTHONUNBUFFERED"] = "1"
    log_dir = Path(tempfile.mkdtemp(prefix="pigp-sim-ioc-"))
    log_path = log_dir / "ioc.log"
    with open(log_path, "wb") as log:
        process = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env)
    handle = SimIOCProcess(process, port, names, prefix, log_path, env=server_environment(port))
    try:
        env_cm = patched_environ(handle.client_env) if set_client_env else contextlib.nullcontext()
        with env_cm:
            _wait_ready(handle, startup_timeout)
            yield handle
    finally:
        handle.stop()
        with contextlib.suppress(OSError):
            log_path.unlink()
            log_dir.rmdir()


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
