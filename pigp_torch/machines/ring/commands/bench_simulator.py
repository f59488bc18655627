"""``pigp bench simulator``: samples per second of the fast coupling model and the pyAT path."""

from __future__ import annotations

import json
import sys

from pigp_torch.machines.ring.commands.ring_options import (
    add_machine_arguments,
    simulator_from_args,
)


def cmd_bench_simulator(args) -> int:
    from pigp_torch.machines.ring.throughput import measure_throughput

    sim = simulator_from_args(args)
    res = measure_throughput(
        sim,
        batch=args.batch,
        n_reference=args.n_reference,
        workers=args.threads,
        progress=lambda msg: print(msg, file=sys.stderr),
    )
    if args.json:
        print(json.dumps(res, indent=2))
        return 0
    print(
        f"fast model, batch {res['batch']}, {res['knobs']} knobs, {res['threads']} threads "
        f"(load average {res['load_average_before']} on {res['cpu_count']} CPUs)"
    )
    for dev, r in res["fast"].items():
        print(
            f"  {dev:5s} {r['samples_per_s']:12,.0f} samples/s  "
            f"({r['samples_per_s_loss_rate_only']:,.0f}/s loss rate only)"
        )
        if "samples_per_cpu_s" in r:
            print(f"  {'':5s} {r['samples_per_cpu_s']:12,.0f} samples per CPU-second")
    gpu = res["gpu"]
    if gpu["samples_per_s"] is None:
        print(f"  gpu   not measured: {gpu['reason'] or 'not requested'}")
    else:
        d = max(gpu["max_rel_diff_vs_cpu"].values())
        print(f"  gpu   {gpu['device']}: largest relative difference to the CPU {d:.1e}")
    print(f"pyAT ohmi_envelope reference: {res['reference_samples_per_s']:,.1f} samples/s")
    print(f"speed-up (CPU fast / reference): {res['speedup_cpu_vs_reference']:,.0f}x")
    diff = res["max_rel_diff"]
    print(
        f"max relative difference: eps_y {diff['eps_y']:.1e}, eps_x {diff['eps_x']:.1e}, "
        f"loss rate {diff['loss_rate']:.1e}"
    )
    return 0


def register(sub, bench) -> None:
    """Add ``pigp bench simulator`` to the ``pigp bench`` sub-parsers."""
    b = bench.add_parser(
        "simulator",
        help="samples/s of the fast model vs the pyAT path",
        description="Samples per second of the batched fast coupling model (CPU, and GPU when "
        "available) and of the pyAT ohmi_envelope path, their ratio and their agreement.",
    )
    add_machine_arguments(b, "error seed of the machine (default 1)")
    b.add_argument("--batch", type=int, default=100_000, help="batch size (default 100000)")
    b.add_argument("--n-reference", type=int, default=5, help="pyAT evaluations (default 5)")
    b.add_argument(
        "--threads", type=int, default=None, help="CPU worker threads (default: torch's count)"
    )
    b.add_argument("--json", action="store_true", help="print one JSON object")
    b.set_defaults(func=cmd_bench_simulator)
