"""``pigp demo``: the main job end to end on the embedded simulated ring
(:mod:`pigp_torch.machines.ring.bench.demo`)."""

from __future__ import annotations

from pathlib import Path

from pigp_torch.surrogate.defaults import TRAIN_DEFAULTS


def cmd_demo(args) -> int:
    from pigp_torch._utils.pool import default_workers
    from pigp_torch.machines.ring.bench.demo import DemoSettings, run_demo
    from pigp_torch.machines.ring.commands.compare import write_comparison

    settings = DemoSettings(
        model_seed=args.model_seed,
        machine_seed=args.machine_seed,
        n=args.n,
        members=args.members,
        budget=args.budget,
        methods=tuple(args.methods),
        target=args.target,
        center_ensemble=args.center_ensemble,
        cache_dir=args.cache_dir,
        no_cache=args.no_cache,
        workers=default_workers() if args.workers is None else args.workers,
    )
    df, prior = run_demo(settings)
    args.out.mkdir(parents=True, exist_ok=True)
    prior.save(args.out / "prior.json")
    units = dict.fromkeys(prior.knob_names, "A")  # the SPEAR3 windings' currents
    write_comparison(df, args.out, f"demo: machine seed {args.machine_seed}", units)
    return 0


def register(sub, bench) -> None:
    """Add ``pigp demo`` to the top-level sub-parsers ``sub``."""
    p = sub.add_parser(
        "demo",
        help="the main job end to end on the embedded simulated ring",
        description="Simulated data of a model ring -> surrogate -> physics prior -> the physics "
        "form fitted online (pigp-physics), the paper's PI-GP and ML-II on another simulated "
        "machine -> table and figure (a few minutes on 2 cores). The surrogate's prior and the "
        "ensemble optima are cached between runs (--cache-dir, --no-cache).",
    )
    p.add_argument("--model-seed", type=int, default=0, help="error seed of the model ring")
    p.add_argument("--machine-seed", type=int, default=1, help="error seed of the machine")
    p.add_argument("--n", type=int, default=100_000, help="simulated samples (default 100000)")
    p.add_argument("--members", type=int, default=3, help="surrogate networks (default 3)")
    p.add_argument("--budget", type=int, default=100, help="evaluations per method")
    p.add_argument(
        "--methods",
        nargs="+",
        default=["pigp-physics", "pigp", "ml2"],
        help="methods compared (default: pigp-physics pigp ml2)",
    )
    p.add_argument(
        "--target",
        default=TRAIN_DEFAULTS["target"],
        help="surrogate target (default inv_sq_excess; log_excess is safer with little data)",
    )
    p.add_argument(
        "--center-ensemble",
        type=int,
        default=20,
        metavar="N",
        help="simulated rings whose optima give pigp-physics its prior on where the machine's "
        "optimum lies and the mean shape of the peak (a few seconds per ring; at least 14, one "
        "more than "
        "the 13 knobs; 0: none; default 20)",
    )
    p.add_argument(
        "--cache-dir",
        type=Path,
        default=None,
        help="where the surrogate's prior and the ensemble optima are kept between runs "
        "(default $PIGP_CACHE_DIR, else ~/.cache/pigp; keyed by the arguments and the code)",
    )
    p.add_argument(
        "--no-cache", action="store_true", help="recompute everything; read and write no cache"
    )
    p.add_argument(
        "--workers",
        type=int,
        default=None,
        metavar="N",
        help="processes for the independent jobs: the surrogate's networks, the ensemble rings "
        "and the methods' runs (default: the CPUs available, at most 2; 1: all in this process). "
        "The numbers do not depend on it",
    )
    p.add_argument("-o", "--out", type=Path, default=Path("runs/demo"), help="output folder")
    p.set_defaults(func=cmd_demo)
