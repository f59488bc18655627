"""``pigp bench ares``: the ARES-EA linac task as published (trials × methods, beam per step)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

#: The wrong-model cases as ``--help`` states them (torch-free, so that ``pigp --help`` stays
#: fast; the cases themselves are :mod:`pigp_torch.machines.ares_ea.cases`, which a test keeps in
#: step with this text).
MODEL_ERROR_HELP: dict[str, str] = {
    "none": "the published trial",
    "beam-outside": "incoming centroids, sizes and divergences 1.25-2x the prior range's limits",
    "misalign-3x": "misalignments 3x the trial's (+-1.5 mm, 3x the prior range)",
    "quad-cal-10": "quadrupoles act with 1.10 x the set k1",
}


#: The methods that run with the ARES model's prior, as ``--help`` names them (torch-free; a
#: test keeps it equal to :data:`pigp_torch.machines.ares_ea.prior.ARES_PRIOR_METHODS`).
ARES_PRIOR_METHODS_HELP: tuple[str, ...] = ("pigp", "pigp-fast")


def _nonnegative_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number in m, got {text!r}") from None
    if not (0.0 <= value < float("inf")):
        raise argparse.ArgumentTypeError(f"expected a finite number >= 0 m, got {text!r}")
    return value


def cmd_bench_ares(args) -> int:
    import json

    import torch

    from pigp_torch.machines.ares_ea.benchmark import (
        check_ares_methods,
        default_ares_methods,
        format_summary,
        plot_mae_vs_step,
        run_ares_benchmark,
        score_runs,
        summarize_scores,
    )
    from pigp_torch.machines.ares_ea.cases import CASE_TEXT, check_case
    from pigp_torch.machines.ares_ea.simulation import load_trials, parse_trial_ids

    check_case(args.model_error)

    torch.set_num_threads(1)
    if args.steps < 1:
        raise ValueError(f"--steps must be >= 1, got {args.steps}")
    trials = load_trials(args.trials)
    if args.trial_ids is None:
        ids = sorted(trials)
    else:
        ids = parse_trial_ids(args.trial_ids)
        missing = [i for i in ids if i not in trials]
        if missing:
            raise ValueError(f"trial ids not in {args.trials or 'the shipped trials'}: {missing}")
    methods = [s.name for s in check_ares_methods(args.methods or default_ares_methods())]
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)

    def progress(line: str) -> None:
        if not args.quiet:
            print(line, file=sys.stderr, flush=True)

    table = run_ares_benchmark(
        [trials[i] for i in ids],
        methods,
        steps=args.steps,
        noise=args.noise,
        seed=args.seed,
        workers=args.workers,
        progress=progress,
        model_error=args.model_error,
    )
    table.to_csv(out / "steps.csv", index=False)
    scores = score_runs(table)
    scores.to_csv(out / "scores.csv", index=False)
    summary = summarize_scores(scores)
    summary.to_csv(out / "summary.csv", index=False)
    plot_mae_vs_step(table, out / "mae_vs_step.png")
    run = {
        "trials": args.trials or "shipped trials_000-149.yaml",
        "trial_ids": ids,
        "methods": methods,
        "steps": args.steps,
        "noise_m": args.noise,
        "seed": args.seed,
        "model_error": args.model_error,
        "model_error_text": CASE_TEXT[args.model_error],
    }
    (out / "run.json").write_text(json.dumps(run, indent=1) + "\n")
    print(
        f"ARES-EA: {len(ids)} trials, {args.steps} steps, screen noise "
        f"{args.noise * 1e6:g} um, machine: {args.model_error} ({CASE_TEXT[args.model_error]}); "
        "MAE noise-free, after setting back to the recommended setting"
    )
    print(format_summary(summary))
    print(f"wrote {out / 'steps.csv'}, scores.csv, summary.csv, run.json, mae_vs_step.png")
    return 0


def register(sub, bench) -> None:
    """Add ``pigp bench ares`` to the ``pigp bench`` sub-parsers."""
    b = bench.add_parser(
        "ares",
        help="the ARES-EA linac task (DESY): methods on published trials, beam per step",
        description="Tune the beam on the ARES-EA screen to each trial's target (mu_x, sigma_x, "
        "mu_y, sigma_y) with each method, starting at [10, -10, 0, 10, 0]; write DIR/steps.csv "
        "(trial, method, step, the four numbers read (m), mae = their mean absolute error to "
        "the target (m), mae_true = the same noise-free), per-run scores, a summary (median "
        "and IQR of final and best MAE in um, steps to 40 and 20 um and the share reaching "
        "them) and a figure of median MAE against step.",
    )
    b.add_argument(
        "--trials",
        default=None,
        help="trials file in the published format (YAML, integer keys; default: the shipped "
        "trials 0-149)",
    )
    b.add_argument(
        "--trial-ids", default=None, help="trial keys, e.g. 50-149 or 0,3,7-9 (default: all)"
    )
    b.add_argument(
        "--methods",
        nargs="+",
        default=None,
        help="registered method names (default: the product's ARES method and the published "
        "recipes published-bo, published-nm); "
        + ", ".join(ARES_PRIOR_METHODS_HELP)
        + " run with the paper's physics prior from the ARES model for each trial's target "
        "(unknowns at the centre of their ranges, never the trial's) and read minus the MAE in "
        "um; other methods that need a ring's physics prior are refused",
    )
    b.add_argument("--steps", type=int, default=150, help="measurements per run (default 150)")
    b.add_argument(
        "--noise",
        type=_nonnegative_float,
        default=0.0,
        help="screen noise: standard deviation of each beam number in m (default 0)",
    )
    b.add_argument(
        "--model-error",
        default="none",
        metavar="CASE",
        help="the simulated machine departs from the model (the methods' models keep the "
        "published ranges): "
        + "; ".join(f"{k}: {v}" for k, v in MODEL_ERROR_HELP.items())
        + " (default none)",
    )
    b.add_argument("--seed", type=int, default=0, help="base seed (run seed = seed + trial)")
    b.add_argument("--workers", type=int, default=1, help="processes (default 1)")
    b.add_argument("-o", "--output", required=True, help="output folder")
    b.add_argument("--quiet", action="store_true", help="no per-run progress lines")
    b.set_defaults(func=cmd_bench_ares)
