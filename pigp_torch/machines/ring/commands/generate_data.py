"""``pigp generate-data``: sample a simulated ring and write a dataset (NPZ)."""

from __future__ import annotations

import sys
from pathlib import Path

from pigp_torch.machines.ring.commands.ring_options import (
    add_machine_arguments,
    simulator_from_args,
)


def cmd_generate_data(args) -> int:
    from pigp_torch.data.sampling import generate_dataset

    if args.n < 1:  # before the machine is built and its optimum searched (seconds)
        raise ValueError(f"n must be positive, got {args.n}")
    sim = simulator_from_args(args)
    print(f"machine: {sim!r}", file=sys.stderr)
    ds = generate_dataset(
        sim, args.n, seed=args.sample_seed, global_fraction=args.global_fraction, progress=True
    )
    path = ds.save(args.output)
    lr = ds.loss_rate
    _, f_star = sim.optimum()  # cached by the sampling design
    print(
        f"wrote {len(ds)} samples to {path} (loss rate {float(lr.min()):.3f}–"
        f"{float(lr.max()):.3f} mA/min, background f_inf {ds.f_inf:.3f} mA/min, optimum "
        f"{f_star:.3f} mA/min)"
    )
    if not sim.spec.is_spear3 and f_star < 1.7 - 1e-3:
        print(
            f"note: this ring's {sim.dim} knobs raise the Touschek density too little for 0.5 → "
            "1.7 mA/min with a non-negative background, so its loss-rate map keeps 0.5 mA/min at "
            f"zero knobs and a background of {ds.f_inf:.3f} mA/min; the optimum is "
            f"{f_star:.3f} mA/min"
        )
    return 0


def register(sub, bench) -> None:
    """Add ``pigp generate-data`` to the top-level sub-parsers ``sub``."""
    p = sub.add_parser(
        "generate-data",
        help="sample the simulated ring and write a dataset (NPZ)",
        description="Sample the 13-D skew-knob space of one simulated machine (Sobol over the box "
        "plus Gaussian clouds around its optimum) and write knobs, emittances and loss rates with "
        "their metadata to an NPZ file.",
    )
    add_machine_arguments(p, "error seed of the simulated model ring (default 1)")
    p.add_argument("--n", type=int, default=100_000, help="number of samples (default 100000)")
    p.add_argument("-o", "--output", type=Path, required=True, help="output .npz file")
    p.add_argument("--sample-seed", type=int, default=0, help="seed of the sampling design")
    p.add_argument(
        "--global-fraction",
        type=float,
        default=0.4,
        help="fraction of samples spread over the whole box (default 0.4)",
    )
    p.set_defaults(func=cmd_generate_data)
