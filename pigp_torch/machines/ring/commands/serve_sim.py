"""``pigp serve-sim``: serve a simulated SPEAR3-like ring over EPICS Channel Access (127.0.0.1)."""

from __future__ import annotations

import sys

from pigp_torch.machines.ring.commands.ring_options import add_ring_arguments, ring_spec_from_args


def cmd_serve_sim(args) -> int:
    import torch

    from pigp_torch.machines.ring.simulated_epics.ioc import serve, sim_ioc_from_args

    torch.set_num_threads(1)
    ring = ring_spec_from_args(args)
    print(f"building simulated ring {ring.describe(args.seed)}", flush=True)
    ioc = sim_ioc_from_args(args, ring)
    print(
        f"clients: EPICS_CA_ADDR_LIST=127.0.0.1:{args.port} EPICS_CA_AUTO_ADDR_LIST=NO; "
        "stop with Ctrl-C",
        file=sys.stderr,
        flush=True,
    )
    serve(ioc, args.port)  # prints the PV names once the server is up; returns on Ctrl-C
    print("simulated IOC stopped", file=sys.stderr)
    return 0


def register(sub, bench) -> None:
    """Add ``pigp serve-sim`` to the top-level sub-parsers ``sub`` (nothing under ``bench``)."""
    from pigp_torch.machines.ring.simulated_epics import add_ioc_arguments

    p = sub.add_parser(
        "serve-sim",
        help="serve a simulated ring over EPICS Channel Access on 127.0.0.1",
        description="Run a caproto IOC in the foreground that serves one simulated SPEAR3-like "
        "ring on 127.0.0.1: per knob <knob>:CurrSetpt (puts outside the bounds refused) and "
        "<knob>:Curr1, the loss rate <prefix>BeamLossRate with Gaussian noise (its CA timestamp "
        "is the time of its last refresh), and the fault-injection switches "
        "<prefix>Sim:ReadbackDelay, <prefix>Sim:NanReadings, <prefix>Sim:Frozen (stop the "
        "refreshes) and <prefix>Sim:RebootOnRead (knobs back to their power-on values at the "
        "N-th read). SIGTERM and Ctrl-C stop it, also when started in the background.",
    )
    add_ioc_arguments(p)
    add_ring_arguments(p)
    p.set_defaults(func=cmd_serve_sim)
