"""``pigp compare`` and ``pigp bench spear3`` (one command, two names): benchmark optimizers on
simulated rings (the spear3-13 protocol, :func:`pigp_torch.machines.ring.bench.run_benchmark`)."""

from __future__ import annotations

from pathlib import Path

from pigp_torch.machines.ring.commands.ring_options import add_ring_arguments


def seed_list(text: str) -> list[int]:
    """``"1-12"`` or ``"1,3,5"`` or ``"1-4,9"`` -> list of ints."""
    seeds = []
    for part in text.split(","):
        if "-" in part:
            a, b = (int(v) for v in part.split("-"))
            seeds.extend(range(a, b + 1))
        elif part.strip():
            seeds.append(int(part))
    return seeds


def format_summary(summary, fraction: int = 95) -> str:
    """The summary table as printed: one row per method in at most 100 columns (medians, and the
    interquartile range of the steps; every column of ``summary.csv`` is in the file).

    Args:
        summary: :func:`~pigp_torch.machines.ring.bench.summarize`'s table (indexed by method).
        fraction: the gain fraction of its ``steps_to_<fraction>`` column.
    """
    import math
    import textwrap

    def num(v, spec):
        return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else format(v, spec)

    def col(row, name):
        return row[name] if name in row.index else float("nan")

    head = (
        f"{'method':<17}{'runs':>5}{'reached':>9}{f'steps to {fraction} %':>18}"
        f"{'gain@20':>9}{'gain@40':>9}{'gain@100':>9}{'best':>10}{'ask':>8}"
    )
    unit = f"{'':<17}{'':>5}{f'{fraction} %':>9}{'median [IQR]':>18}{'':>27}{'mA/min':>10}{'s':>8}"
    lines = [head, unit]
    for method, row in summary.iterrows():
        steps = col(row, f"steps_to_{fraction}_median")
        iqr = (col(row, f"steps_to_{fraction}_q25"), col(row, f"steps_to_{fraction}_q75"))
        budget = col(row, "budget")
        spread = "" if math.isnan(steps) else f" [{num(iqr[0], '.0f')}-{num(iqr[1], '.0f')}]"
        if not math.isnan(budget) and not steps <= budget:  # not reached within the budget
            steps, spread = f">{budget:.0f}", ""
        reached = f"{int(col(row, f'n_reached_{fraction}'))}/{int(col(row, 'n_runs'))}"
        lines.append(
            f"{str(method)[:16]:<17}{int(col(row, 'n_runs')):>5}{reached:>9}"
            f"{(steps if isinstance(steps, str) else num(steps, '.0f')) + spread:>18}"
            f"{num(col(row, 'gain_20_median'), '.3f'):>9}"
            f"{num(col(row, 'gain_40_median'), '.3f'):>9}"
            f"{num(col(row, 'gain_100_median'), '.3f'):>9}"
            f"{num(col(row, 'best_f_true_median'), '.4f'):>10}"
            f" {num(col(row, 'ask_time_s_median'), '.3g'):>7}"  # a space even at 8 characters
        )
    note = (
        "gain@k: fraction of the way from the start to the machine's true optimum after k "
        "evaluations (median; 1 = optimum); best: best noise-free loss rate; ask: median seconds "
        "per proposal. Every column with its quartiles: summary.csv"
    )
    return "\n".join([*lines, *textwrap.wrap(note, 100)])


def write_comparison(df, out: Path, title: str, knob_units: dict[str, str]) -> None:
    """``runs.csv`` and ``summary.csv`` (headers with units, ``name [unit]``; ``knob_units``:
    knob name -> unit), the figures and the printed summary of a benchmark table ``df``."""
    from pigp_torch.data.tables import with_units
    from pigp_torch.machines.ring.bench import plot_prior_mean, plot_runs, summarize

    out.mkdir(parents=True, exist_ok=True)
    with_units(df, knob_units).to_csv(out / "runs.csv", index=False)
    summary = summarize(df)
    with_units(summary, knob_units).to_csv(out / "summary.csv")
    plot_runs(df, out / "fig2b_runs.png", title=title)
    files = ["runs.csv", "summary.csv", "fig2b_runs.png"]
    if {"pigp", "pigp-zero-mean"} <= set(df["method"]):
        plot_prior_mean(df, out / "fig2c_prior_mean.png")
        files.append("fig2c_prior_mean.png")
    print(format_summary(summary))
    print(f"wrote {', '.join(files)} to {out}")


def cmd_compare(args) -> int:
    from pigp_torch.machines.ring.bench import run_benchmark
    from pigp_torch.machines.ring.commands.ring_options import ring_spec_from_args
    from pigp_torch.machines.ring.ensemble import check_ensemble_size
    from pigp_torch.machines.ring.spec import knob_count

    ring = ring_spec_from_args(args)
    check_ensemble_size(args.center_ensemble, knob_count(ring))  # before any ring is computed
    df = run_benchmark(
        args.methods,
        seed_list(args.seeds),
        model_seed=args.model_seed,
        budgets={"gp": args.budget_gp, "direct": args.budget_direct},
        n_workers=args.workers,
        progress=True,
        ring=ring,
        scheduler=args.scheduler,
        center_ensemble=args.center_ensemble,
        machine_maps=not args.model_maps,
        prior_source=args.prior_source,
        family=args.family,
    )
    model = ring.build(args.model_seed)  # cached: the model ring was built already
    n_knobs = model.dim
    name = "spear3" if ring.is_spear3 else Path(ring.lattice).stem
    title = f"{name}-{n_knobs}, model seed {args.model_seed}"
    if args.family != "project":
        title += f", {args.family} machines"
    write_comparison(df, args.out, title, dict.fromkeys(model.knob_names, model.knob_units))
    return 0


#: What ``pigp compare`` and ``pigp bench spear3`` do, as their help says it.
DESCRIPTION = (
    "Run methods x machine error seeds from skews zero with 0.04 mA/min noise, the physics prior "
    "computed from a different model ring; score every evaluation on the noise-free loss rate; "
    "write runs.csv, summary.csv and Fig. 2b/2c-style figures."
)


def register(sub, bench) -> None:
    """Add ``pigp compare`` to the top-level sub-parsers ``sub`` (the name users know; ``pigp
    bench spear3`` is the same command, :func:`register_bench`)."""
    help_ = "benchmark optimizers on simulated machines (spear3-13 protocol)"
    add_compare_arguments(sub.add_parser("compare", help=help_, description=DESCRIPTION))


def register_bench(bench) -> None:
    """Add ``pigp bench spear3`` (the ring kind's benchmark: ``pigp compare``) to ``bench``."""
    help_ = "the SPEAR3 ring's task (spear3-13 protocol; the same as pigp compare)"
    add_compare_arguments(bench.add_parser("spear3", help=help_, description=DESCRIPTION))


def add_compare_arguments(p) -> None:
    """The options of ``pigp compare`` / ``pigp bench spear3`` on parser ``p`` (runs
    :func:`cmd_compare`)."""
    p.add_argument(
        "--methods",
        nargs="+",
        default=[
            "pigp-physics",
            "pigp",
            "pigp-zero-mean",
            "ml2",
            "xopt-ucb",
            "xopt-ucb-travel",
            "nelder-mead",
            "rcds",
        ],
        help="method names (default: pigp-physics pigp pigp-zero-mean ml2 xopt-ucb "
        "xopt-ucb-travel nelder-mead rcds; the xopt ones need Xopt installed)",
    )
    p.add_argument("--seeds", default="1-24", help="machine error seeds, e.g. 1-24 or 1,3,5")
    p.add_argument(
        "--prior-source",
        default="surrogate",
        choices=["surrogate", "exact"],
        help="surrogate (default: the paper's chain, simulated data of the model ring -> "
        "3-network surrogate -> autograd Hessian; minutes) or exact (the model ring's own "
        "differentiable loss rate)",
    )
    p.add_argument(
        "--model-maps",
        action="store_true",
        help="give every machine the model's loss-rate constants (default: each machine its "
        "own background and Touschek scale, drawn from its seed)",
    )
    p.add_argument(
        "--family",
        choices=["project", "wide"],
        default="project",
        help="machine family: project (default: the user deck, coupling calibrated to 0.71 %%) "
        "or wide (per machine: tunes moved by up to +-0.02, the error scale between the "
        "ensemble's extremes, peak 0.9-1.7 mA/min and background 0.05-0.35 mA/min; SPEAR3 user "
        "deck only, without --model-maps)",
    )
    p.add_argument("--model-seed", type=int, default=0, help="error seed of the model ring")
    p.add_argument("--budget-gp", type=int, default=100, help="evaluations for GP methods")
    p.add_argument("--budget-direct", type=int, default=300, help="for Nelder-Mead and RCDS")
    p.add_argument(
        "--workers",
        type=int,
        default=1,
        help="parallel processes here (with --scheduler local: Dask worker processes)",
    )
    p.add_argument(
        "--scheduler",
        default=None,
        metavar="ADDRESS",
        help="run the methods x seeds grid on a Dask cluster, one task per run: a scheduler "
        "address (tcp://host:8786) or 'local' (a LocalCluster of --workers processes on "
        "127.0.0.1); same numbers as a local run (default: local processes, no Dask)",
    )
    add_ring_arguments(p)
    p.add_argument(
        "--center-ensemble",
        type=int,
        default=40,
        metavar="N",
        help="model rings (error seeds 1001...) whose optima give pigp-physics its prior on "
        "where the machine's optimum lies and the mean shape of the peak (a few seconds per "
        "ring; 0: "
        "box prior and the model ring's shape; otherwise more than the knobs, at least 14 for "
        "the 13 SPEAR3 knobs; default 40)",
    )
    p.add_argument("-o", "--out", type=Path, default=Path("runs/compare"), help="output folder")
    p.set_defaults(func=cmd_compare)
