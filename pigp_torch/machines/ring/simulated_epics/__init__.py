r"""Test servers: the simulated ring served over EPICS (Channel Access IOC, pvAccess server),
for tests and demos (``pigp serve-sim``); no part of an online run.

* :mod:`.ioc` — a caproto IOC (``caproto.server``) that serves a simulated ring (SPEAR3 by
  default, knobs in amps) with noise: per knob a setpoint PV ``<knob>:CurrSetpt`` and a readback
  ``<knob>:Curr1``, the loss rate ``<prefix>BeamLossRate`` and fault-injection switches;
  :func:`~.ioc.start_sim_ioc` launches it in a subprocess on the loopback interface.
* :mod:`.pva` — the same ring as a pvAccess server (p4p, the ``pva`` extra).
* The client side is :class:`pigp_torch.machine.epics.EpicsMachine` (and
  :class:`~pigp_torch.machine.pva.PvaMachine`), in the core.

Why the servers live whole in the ring's folder (and not as a generic IOC in the core with the
ring plugged in): everything they serve is the ring's — the PV names (``SPEAR:BeamLossRate``,
the windings' ``:CurrSetpt``/``:Curr1``), the knob sets (``paper13``), the units (A, mA/min), the
loss-rate limits, the ring's description passed to the subprocess (a
:class:`~..spec.RingSpec`) — and the part that would be generic (caproto's and p4p's server loop,
a setpoint/readback pair per knob) is what those libraries already are. No other kind serves
EPICS today; a second one would share caproto and p4p, not these modules. The old paths
(``pigp_torch.simulated_epics.*``, ``pigp_torch.testing.*``) import as these modules.

This package imports nothing heavy (no caproto, no torch): the ``pigp`` command-line parser uses
:func:`add_ioc_arguments` at start-up. Import :mod:`.ioc` for the server itself.
"""

from __future__ import annotations

import argparse
import socket

#: Default prefix of the ring-wide PVs (loss rate and simulator switches).
DEFAULT_PREFIX = "SPEAR:"
#: PV name suffixes (appended to the prefix / knob name).
LOSS_RATE_SUFFIX = "BeamLossRate"
SETPOINT_SUFFIX = ":CurrSetpt"
READBACK_SUFFIX = ":Curr1"
NAN_READINGS_SUFFIX = "Sim:NanReadings"
READBACK_DELAY_SUFFIX = "Sim:ReadbackDelay"
FROZEN_SUFFIX = "Sim:Frozen"
REBOOT_ON_READ_SUFFIX = "Sim:RebootOnRead"
GLITCH_READINGS_SUFFIX = "Sim:GlitchReadings"
GLITCH_VALUE_SUFFIX = "Sim:GlitchValue"
STUCK_KNOB_SUFFIX = "Sim:StuckKnob"
READBACK_OFFSET_SUFFIX = "Sim:ReadbackOffset"
NARROW_KNOB_SUFFIX = "Sim:NarrowKnob"
NARROW_LIMIT_SUFFIX = "Sim:NarrowLimit"
STALL_PUTS_SUFFIX = "Sim:StallPuts"
#: Alarm-severity fault injection: the severity served, on how many loss-rate reads, on which
#: knob's readback.
ALARM_SEVERITY_SUFFIX = "Sim:AlarmSeverity"
ALARM_READINGS_SUFFIX = "Sim:AlarmReadings"
ALARM_KNOB_SUFFIX = "Sim:AlarmKnob"
#: Display limits (LOPR/HOPR) of the simulated loss-rate PV, mA/min.
LOSS_RATE_LIMITS = (0.0, 100.0)
#: Loopback: the simulated IOC never listens on an outside interface.
LOOPBACK = "127.0.0.1"
#: Default Channel Access port of the simulated IOC (UDP search and first TCP port tried): not
#: CA's own 5064/5065 (server, repeater), which any IOC or gateway on a control-room host already
#: holds, nor pvAccess's 5075/5076; below the ephemeral range (Linux: 32768-60999), so no client
#: socket is handed it. Clients find it with ``EPICS_CA_ADDR_LIST=127.0.0.1:5164``.
SIM_CA_PORT = 5164


def add_ioc_arguments(p: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Options of the simulated IOC (``pigp serve-sim``,
    ``python -m pigp_torch.machines.ring.simulated_epics.ioc``) other than the ring: ``--seed
    --noise --noise-seed --prefix --port --update-period --readback-delay --put-log``. The ring
    itself is a
    :class:`~pigp_torch.machines.ring.spec.RingSpec`: ``pigp serve-sim`` builds it from its ring
    options (:mod:`pigp_torch.commands.ring_options`),
    ``python -m pigp_torch.machines.ring.simulated_epics.ioc`` reads it as JSON (``--ring``)."""
    p.add_argument(
        "--seed", type=int, default=1, help="error seed of the simulated ring (default 1)"
    )
    p.add_argument(
        "--noise",
        type=float,
        default=0.04,
        help="standard deviation of the loss-rate noise, mA/min (default 0.04)",
    )
    p.add_argument("--noise-seed", type=int, default=0, help="seed of the noise (default 0)")
    p.add_argument(
        "--prefix",
        default=DEFAULT_PREFIX,
        help=f"prefix of the loss-rate and simulator PVs (default {DEFAULT_PREFIX!r})",
    )
    p.add_argument(
        "--port",
        type=int,
        default=SIM_CA_PORT,
        help=f"Channel Access server port, UDP search and first TCP port tried (default "
        f"{SIM_CA_PORT}: not CA's standard 5064/5065, which a control-room host's own IOCs and "
        "gateways hold, nor pvAccess's 5075/5076; clients set "
        f"EPICS_CA_ADDR_LIST=127.0.0.1:{SIM_CA_PORT} EPICS_CA_AUTO_ADDR_LIST=NO)",
    )
    p.add_argument(
        "--update-period",
        type=float,
        default=0.1,
        help="seconds between loss-rate updates (default 0.1)",
    )
    p.add_argument(
        "--readback-delay",
        type=float,
        default=0.0,
        help="seconds before a knob readback follows its setpoint (default 0)",
    )
    p.add_argument(
        "--put-log",
        default=None,
        metavar="FILE",
        help="append every put the IOC receives to FILE (JSON lines: PV, value, the setpoint "
        "before the put, time), for fault-injection tests (default: no put log)",
    )
    return p


def free_ports(n: int = 1, attempts: int = 50) -> list[int]:
    """``n`` distinct ports free for TCP and UDP on 127.0.0.1 (chosen by the OS; bounded)."""
    ports: list[int] = []
    for _ in range(attempts):
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as tcp:
            tcp.bind((LOOPBACK, 0))
            port = tcp.getsockname()[1]
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp:
                try:
                    udp.bind((LOOPBACK, port))
                except OSError:
                    continue
        if port not in ports:
            ports.append(port)
        if len(ports) == n:
            return ports
    raise RuntimeError(f"no {n} free TCP+UDP ports on {LOOPBACK} after {attempts} attempts")


__all__ = [
    "ALARM_KNOB_SUFFIX",
    "ALARM_READINGS_SUFFIX",
    "ALARM_SEVERITY_SUFFIX",
    "DEFAULT_PREFIX",
    "FROZEN_SUFFIX",
    "GLITCH_READINGS_SUFFIX",
    "GLITCH_VALUE_SUFFIX",
    "LOOPBACK",
    "LOSS_RATE_LIMITS",
    "LOSS_RATE_SUFFIX",
    "NAN_READINGS_SUFFIX",
    "NARROW_KNOB_SUFFIX",
    "NARROW_LIMIT_SUFFIX",
    "READBACK_DELAY_SUFFIX",
    "READBACK_OFFSET_SUFFIX",
    "READBACK_SUFFIX",
    "REBOOT_ON_READ_SUFFIX",
    "SETPOINT_SUFFIX",
    "SIM_CA_PORT",
    "STALL_PUTS_SUFFIX",
    "STUCK_KNOB_SUFFIX",
    "add_ioc_arguments",
    "free_ports",
]
