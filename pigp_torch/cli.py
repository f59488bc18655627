"""The ``pigp`` command: data generation, surrogate training, priors, optimization, benchmarks.

Run ``pigp --help`` or ``pigp COMMAND --help``. Heavy imports happen inside each command so that
``pigp --help`` answers at once.
"""

from __future__ import annotations

import os

# The simulator multiplies many stacks of 6x6 matrices with numpy; a multi-threaded OpenBLAS makes
# them up to 10x slower on a busy machine. Must be set before numpy is first imported.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import json
import sys
from pathlib import Path


def _simulator(args):
    from pigp_torch.simulation import Spear3Coupling

    return Spear3Coupling(error_seed=args.seed, knobs=args.knobs, optics=args.optics)


def _add_machine_args(p: argparse.ArgumentParser, seed_help: str) -> None:
    p.add_argument("--seed", type=int, default=1, help=seed_help)
    p.add_argument(
        "--knobs", default="paper13", help="paper13 (default), powered14 or all72 skew windings"
    )
    p.add_argument(
        "--optics", default="achromat", choices=["achromat", "low_emittance"], help="ring optics"
    )


# ----------------------------------------------------------------------------- generate-data
def cmd_generate_data(args) -> int:
    from pigp_torch.simulation.sampling import generate_dataset

    sim = _simulator(args)
    print(f"machine: {sim!r}", file=sys.stderr)
    ds = generate_dataset(
        sim, args.n, seed=args.sample_seed, global_fraction=args.global_fraction, progress=True
    )
    path = ds.save(args.output)
    lr = ds.loss_rate
    print(
        f"wrote {len(ds)} samples to {path} (loss rate {float(lr.min()):.3f}–"
        f"{float(lr.max()):.3f} mA/min, f_inf {ds.f_inf:.3f})"
    )
    return 0


# ----------------------------------------------------------------------------- bench
def cmd_bench_simulator(args) -> int:
    import torch

    from pigp_torch.simulation.throughput import measure_throughput

    sim = _simulator(args)
    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    res = measure_throughput(sim, batch=args.batch, n_reference=args.n_reference, devices=devices)
    if args.json:
        print(json.dumps(res, indent=2))
        return 0
    print(f"fast model, batch {res['batch']}, {res['knobs']} knobs, {res['threads']} threads")
    for dev, r in res["fast"].items():
        print(
            f"  {dev:5s} {r['samples_per_s']:12,.0f} samples/s  "
            f"({r['samples_per_s_loss_rate_only']:,.0f}/s loss rate only)"
        )
    print(f"pyAT ohmi_envelope reference: {res['reference_samples_per_s']:,.1f} samples/s")
    print(f"speed-up (CPU fast / reference): {res['speedup_cpu_vs_reference']:,.0f}x")
    diff = res["max_rel_diff"]
    print(f"max relative difference: eps_y {diff['eps_y']:.1e}, loss rate {diff['loss_rate']:.1e}")
    return 0


# ----------------------------------------------------------------------------- parser
def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="pigp",
        description="Physics-informed Gaussian-process optimization of particle accelerators.",
    )
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser(
        "generate-data",
        help="sample the simulated ring and write a dataset (NPZ)",
        description="Sample the 13-D skew-knob space of one simulated machine (Sobol over the box "
        "plus Gaussian clouds around its optimum) and write knobs, emittances and loss rates with "
        "their metadata to an NPZ file.",
    )
    _add_machine_args(p, "error seed of the simulated model ring (default 1)")
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

    p = sub.add_parser("bench", help="speed benchmarks (print numbers)")
    bench = p.add_subparsers(dest="bench", required=True)
    b = bench.add_parser(
        "simulator",
        help="samples/s of the fast model vs the pyAT path",
        description="Samples per second of the batched fast coupling model (CPU, and GPU when "
        "available) and of the pyAT ohmi_envelope path, their ratio and their agreement.",
    )
    _add_machine_args(b, "error seed of the machine (default 1)")
    b.add_argument("--batch", type=int, default=100_000, help="batch size (default 100000)")
    b.add_argument("--n-reference", type=int, default=5, help="pyAT evaluations (default 5)")
    b.add_argument("--json", action="store_true", help="print one JSON object")
    b.set_defaults(func=cmd_bench_simulator)
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (ValueError, FileNotFoundError) as err:
        print(f"pigp {args.command}: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
