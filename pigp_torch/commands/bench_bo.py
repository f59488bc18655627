"""``pigp bench bo``: step time of the fast physics-informed BO vs the stock BoTorch path."""

from __future__ import annotations

import argparse
import json


def _int_list(text: str) -> list[int]:
    try:
        values = [int(v) for v in text.replace(",", " ").split()]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected integers like 10,50,150; got {text!r}"
        ) from None
    if not values or min(values) < 1:
        raise argparse.ArgumentTypeError(f"expected positive integers, got {text!r}")
    return values


def cmd_bench_bo(args) -> int:
    import torch

    from pigp_torch.bench.bo_speed import DEFAULT_DIMS, DEFAULT_NS, bo_step_times, format_table

    torch.set_num_threads(args.threads)
    result = bo_step_times(
        ns=args.ns or list(DEFAULT_NS),
        dims=args.dims or list(DEFAULT_DIMS),
        repeats=args.repeats,
        stock_repeats=args.stock_repeats,
        ml2=not args.no_ml2,
        ml2_max_n=args.ml2_max_n,
        seed=args.seed,
        progress=not args.quiet,
    )
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        print(format_table(result))
    return 0


def register(sub, bench) -> None:
    """Add ``pigp bench bo`` to the ``pigp bench`` sub-parsers."""
    b = bench.add_parser(
        "bo",
        help="step time of the fast PI-GP BO vs stock BoTorch (and warm-started ML-II)",
        description="Median and 90th-percentile time of one BO step (tell + ask) with "
        "FastBayesOpt (incremental exact posterior, closed-form derivatives) and with the stock "
        "path (SingleTaskGP from scratch + optimize_acqf with UCB, 10 restarts, 256 raw "
        "samples), on a synthetic 1.7-peak problem with a condition-483 precision matrix, at "
        "each observation count n and knob count d; their ratios; and the ML-II GP refitted "
        "(warm-started) at every step.",
    )
    b.add_argument(
        "--ns",
        type=_int_list,
        default=None,
        help="observation counts (default 10,50,150,500)",
    )
    b.add_argument("--dims", type=_int_list, default=None, help="knob counts (default 13,72)")
    b.add_argument("--repeats", type=int, default=20, help="timed fast steps per size (20)")
    b.add_argument(
        "--stock-repeats",
        type=int,
        default=None,
        help="timed stock / ML-II steps per size (default: --repeats)",
    )
    b.add_argument("--no-ml2", action="store_true", help="skip the ML-II path")
    b.add_argument(
        "--ml2-max-n", type=int, default=150, help="time ML-II only up to this n (default 150)"
    )
    b.add_argument("--seed", type=int, default=0, help="seed of problem, design and noise")
    b.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    b.add_argument("--json", action="store_true", help="print one JSON object (on stdout)")
    b.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    b.set_defaults(func=cmd_bench_bo)
