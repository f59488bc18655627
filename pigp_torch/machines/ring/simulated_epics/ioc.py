r"""A simulated ring (SPEAR3 by default) served over EPICS Channel Access (a caproto IOC): building
the IOC (:func:`make_sim_ioc`), serving it (:func:`serve`, ``pigp serve-sim``, ``python -m
pigp_torch.machines.ring.simulated_epics.ioc``).

The PVs and their meaning: :mod:`~.ioc_pvs`; the environment:
:mod:`~.ca_env`; the subprocess launcher for tests:
:mod:`~.ioc_process`.
"""

from __future__ import annotations

import gc
import math
import os
import sys

import torch

from pigp_torch.machines.ring.simulated_epics import (
    DEFAULT_PREFIX,
    LOOPBACK,
    SIM_CA_PORT,
    add_ioc_arguments,
)
from pigp_torch.machines.ring.simulated_epics.ca_env import (
    READY_MESSAGE,
    client_environment,
    free_port,
    patched_environ,
    server_environment,
)
from pigp_torch.machines.ring.simulated_epics.ioc_class import sim_ioc_class
from pigp_torch.machines.ring.simulated_epics.ioc_process import SimIOCProcess, start_sim_ioc
from pigp_torch.machines.ring.simulated_epics.ioc_pvs import SimRingIOC

__all__ = [
    "READY_MESSAGE",
    "SimIOCProcess",
    "SimRingIOC",
    "client_environment",
    "free_port",
    "main",
    "make_sim_ioc",
    "patched_environ",
    "serve",
    "server_environment",
    "sim_ioc_class",
    "sim_ioc_from_args",
    "start_sim_ioc",
]


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
    put_log=None,
) -> SimRingIOC:
    """The IOC of machine ``ring.build(seed)`` (not yet serving).

    Args:
        seed: error seed of the simulated ring.
        knobs: knob set or names (overrides ``ring``'s).
        ring: a :class:`~pigp_torch.machines.ring.spec.RingSpec` (default: SPEAR3, 13 knobs, A).
        noise: loss-rate noise standard deviation (mA/min); ``noise_seed`` seeds it.
        prefix: prefix of the loss-rate and switch PVs.
        update_period: see :class:`SimRingIOC`.
        readback_delay, nan_readings, x_init: see :func:`sim_ioc_class`.
        put_log: file receiving every accepted setpoint put (see :class:`SimRingIOC`).
    """
    from pigp_torch.machine import SimulatedMachine
    from pigp_torch.machines.ring.spec import as_ring_spec

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
    return cls(prefix="", machine=machine, update_period=update_period, put_log=put_log)


# ----------------------------------------------------------------------------- serving
def serve(ioc: SimRingIOC, port: int = SIM_CA_PORT, *, log_pv_names: bool = True) -> None:
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


def sim_ioc_from_args(args, ring=None):
    """The IOC described by the options of
    :func:`pigp_torch.machines.ring.simulated_epics.add_ioc_arguments`
    and the ring ``ring`` (a :class:`~pigp_torch.machines.ring.spec.RingSpec` or its
    :meth:`~pigp_torch.machines.ring.spec.RingSpec.to_dict` form; default: ``args.ring``, that form
    as JSON text, else SPEAR3 with the 13 knobs of the study)."""
    import json

    if ring is None and getattr(args, "ring", None):
        ring = json.loads(args.ring)
    return make_sim_ioc(
        args.seed,
        ring=ring,
        noise=args.noise,
        noise_seed=args.noise_seed,
        prefix=args.prefix,
        update_period=args.update_period,
        readback_delay=args.readback_delay,
        put_log=getattr(args, "put_log", None),
    )


def main(argv=None) -> int:
    """``python -m pigp_torch.machines.ring.simulated_epics.ioc``: serve the simulated ring
    (options as ``serve-sim``)."""
    import argparse

    torch.set_num_threads(1)
    p = argparse.ArgumentParser(
        prog="python -m pigp_torch.machines.ring.simulated_epics.ioc",
        description="Serve a simulated ring (SPEAR3 by default) over EPICS Channel Access on "
        "127.0.0.1.",
    )
    add_ioc_arguments(p)
    p.add_argument(
        "--ring",
        default=None,
        metavar="JSON",
        help="the simulated ring as the JSON form of a RingSpec (RingSpec.to_dict), e.g. "
        '\'{"knobs": ["01G-QSS4"]}\' (default: SPEAR3 user optics, the 13 knobs of the study)',
    )
    args = p.parse_args(argv)
    ioc = sim_ioc_from_args(args)
    # The ring's large, long-lived object graph need not be traversed by the garbage collector,
    # neither while serving nor at exit.
    gc.freeze()
    serve(ioc, args.port)
    print("simulated IOC stopped", flush=True)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
