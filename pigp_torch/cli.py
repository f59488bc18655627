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
    from pigp_torch.ringargs import ring_spec_from_args

    return ring_spec_from_args(args).build(args.seed)


def _add_machine_args(p: argparse.ArgumentParser, seed_help: str) -> None:
    from pigp_torch.ringargs import add_ring_arguments

    p.add_argument("--seed", type=int, default=1, help=seed_help)
    add_ring_arguments(p)


# ----------------------------------------------------------------------------- generate-data
def cmd_generate_data(args) -> int:
    from pigp_torch.simulation.sampling import generate_dataset

    if args.n < 1:  # before the machine is built and its optimum searched (seconds)
        raise ValueError(f"n must be positive, got {args.n}")
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


# ----------------------------------------------------------------------------- train-surrogate
def _train_default(name: str):
    """Default of a train_surrogate argument (the single source of the tuned values)."""
    from pigp_torch.surrogate.defaults import TRAIN_DEFAULTS

    return TRAIN_DEFAULTS[name]


def add_train_arguments(p: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Arguments of ``pigp train-surrogate`` (also used by surrogate_training/train.py)."""
    from pigp_torch.surrogate.defaults import ACTIVATION_NAMES, TARGETS

    d = _train_default
    p.add_argument("data", type=Path, help="dataset NPZ written by `pigp generate-data`")
    p.add_argument("-o", "--output", type=Path, required=True, help="model file to write (.pt)")
    p.add_argument("--members", type=int, default=3, help="networks averaged (default 3)")
    p.add_argument("--widths", type=int, nargs="+", default=list(d("widths")))
    p.add_argument("--epochs", type=int, default=d("max_epochs"), help="maximum epochs")
    p.add_argument("--batch-size", type=int, default=d("batch_size"))
    p.add_argument("--lr", type=float, default=d("lr"), help="peak learning rate")
    p.add_argument("--patience", type=int, default=d("patience"))
    p.add_argument("--val-fraction", type=float, default=d("val_fraction"))
    p.add_argument("--seed", type=int, default=0, help="seed of the first member")
    p.add_argument("--device", default="cpu", help="cpu or cuda")
    p.add_argument("--threads", type=int, default=d("num_threads"), help="CPU threads")
    p.add_argument("--activation", default=d("activation"), choices=list(ACTIVATION_NAMES))
    p.add_argument("--target", default=d("target"), choices=list(TARGETS))
    p.add_argument("--float64", action="store_true", help="train in float64 (default float32)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def format_training_report(report: dict) -> str:
    """Human-readable summary of one training report."""
    lines = [
        f"samples: {report['n_train']} train / {report['n_val']} held out",
        f"epochs: {report['epochs']} (best {report['best_epoch']}), "
        f"training time {report['train_time_s']:.1f} s on {report['device']} ({report['dtype']})",
        f"held-out relative RMSE of the loss rate: {100 * report['val_rel_rmse']:.3f} %",
        f"held-out R^2 of log(loss - f_inf):       {report['val_r2_log_excess']:.6f}",
        f"near optimum (top {report['near_opt_n']} held-out points, loss >= "
        f"{report['near_opt_min_loss_rate']:.3g}): relative RMSE "
        f"{100 * report['near_opt_rel_rmse']:.3f} %, max {100 * report['near_opt_rel_max']:.3f} %",
    ]
    if report["n_clamped"]:
        lines.append(
            f"note: {report['n_clamped']} samples had loss - f_inf < {report['excess_floor']:.3g} "
            "and were clamped before the logarithm"
        )
    return "\n".join(lines)


def cmd_train_surrogate(args) -> int:
    import torch

    from pigp_torch.dataset import Dataset
    from pigp_torch.surrogate import save_surrogate, train_ensemble

    data = Dataset.load(args.data)
    model, reports = train_ensemble(
        data,
        n_members=args.members,
        seed=args.seed,
        widths=tuple(args.widths),
        activation=args.activation,
        target=args.target,
        val_fraction=args.val_fraction,
        batch_size=args.batch_size,
        lr=args.lr,
        max_epochs=args.epochs,
        patience=args.patience,
        device=args.device,
        dtype=torch.float64 if args.float64 else torch.float32,
        num_threads=args.threads,
        progress=not args.quiet,
    )
    if len(reports) == 1:
        model = model.members[0]
    metadata = {
        "knob_names": data.knob_names,
        "bounds": data.bounds.tolist(),
        "f_inf": data.f_inf,
        "data_file": args.data.name,
        "data_metadata": data.metadata,
        # one report, or one per ensemble member
        "metrics": reports[0] if len(reports) == 1 else {"members": reports},
    }
    path = save_surrogate(model, args.output, metadata)
    for k, report in enumerate(reports):
        if len(reports) > 1:
            print(f"--- member {k + 1}/{len(reports)} (seed {report['seed']})")
        print(format_training_report(report))
    print(f"saved surrogate to {path}")
    return 0


# ----------------------------------------------------------------------------- build-prior
def cmd_build_prior(args) -> int:
    import torch

    from pigp_torch.prior import prior_from_model
    from pigp_torch.surrogate import load_surrogate

    model, meta = load_surrogate(args.model)
    bounds = model.bounds
    if args.knob_limit is not None:
        lim = torch.full((model.dim,), args.knob_limit, dtype=torch.float64)
        bounds = torch.stack([-lim, lim])
    data_meta = meta.get("data_metadata") or {}
    provenance = {
        "surrogate_file": str(args.model.name),
        "data_file": meta.get("data_file"),
        "model_error_seed": data_meta.get("error_seed"),
    }
    prior = prior_from_model(
        model,
        bounds,
        f_inf=float(model.f_inf),
        noise=args.noise,
        n_starts=args.starts,
        seed=args.seed,
        knob_names=meta.get("knob_names") or None,
        provenance=provenance,
    )
    if args.center_ensemble < 0:
        raise ValueError(f"--center-ensemble must be >= 0, got {args.center_ensemble}")
    if args.center_ensemble:
        prior = _with_center_ensemble(prior, args.center_ensemble, data_meta)
    path = prior.save(args.output)
    lengths, _ = prior.length_scales(normalized=True)
    print(f"optimum of the surrogate: {prior.f_x0:.4f} mA/min (f_inf {prior.f_inf:.4f})")
    print(f"precision condition number: {prior.condition_number:.0f}")
    print("correlation lengths (normalized knobs, stiffest first): "
          + " ".join(f"{v:.3g}" for v in lengths.tolist()))  # fmt: skip
    print(f"saved prior to {path}")
    return 0


def _with_center_ensemble(prior, size: int, data_meta: dict, machine_seed=None):
    """``prior`` with ``center_cov`` and ``peak_shape`` from ``size`` simulated rings of the
    data's optics; neither the model ring nor the machine under test may be one of them."""
    import dataclasses

    from pigp_torch.simulation.ensemble import ensemble_optima, ensemble_seeds
    from pigp_torch.simulation.spec import RingSpec, as_ring_spec

    if data_meta.get("ring"):
        spec = RingSpec.from_dict(data_meta["ring"])
    else:  # data written without a ring record: the SPEAR3 ring with the prior's knobs
        spec = as_ring_spec(None, knobs=tuple(prior.knob_names))
    seeds = ensemble_seeds(size)
    for what, seed in (("model ring", data_meta.get("error_seed")), ("machine", machine_seed)):
        if seed in seeds:
            raise ValueError(f"the {what} (error seed {seed}) is among the ensemble seeds "
                             f"{seeds[0]}-{seeds[-1]}")  # fmt: skip
    print(f"optima of {size} ensemble rings (error seeds {seeds[0]}-{seeds[-1]})", flush=True)
    model = spec.build(data_meta.get("error_seed", seeds[0]))
    if list(model.knob_names) != list(prior.knob_names):
        raise ValueError("the data's ring has other knobs than the prior")
    optima = ensemble_optima(seeds, model=model, progress=True)
    provenance = {**prior.provenance, "center_ensemble_seeds": optima.seed_range}
    return dataclasses.replace(prior, **optima.prior_fields(), provenance=provenance)


# ----------------------------------------------------------------------------- compare
def _seed_list(text: str) -> list[int]:
    """``"1-12"`` or ``"1,3,5"`` or ``"1-4,9"`` -> list of ints."""
    seeds = []
    for part in text.split(","):
        if "-" in part:
            a, b = (int(v) for v in part.split("-"))
            seeds.extend(range(a, b + 1))
        elif part.strip():
            seeds.append(int(part))
    return seeds


def _write_comparison(df, out: Path, title: str) -> None:
    from pigp_torch.benchmark import plot_prior_mean, plot_runs, summarize

    out.mkdir(parents=True, exist_ok=True)
    df.to_csv(out / "runs.csv", index=False)
    summary = summarize(df)
    summary.to_csv(out / "summary.csv")
    plot_runs(df, out / "fig2b_runs.png", title=title)
    files = ["runs.csv", "summary.csv", "fig2b_runs.png"]
    if {"pigp", "pigp-zero-mean"} <= set(df["method"]):
        plot_prior_mean(df, out / "fig2c_prior_mean.png")
        files.append("fig2c_prior_mean.png")
    with_pd_options = summary.to_string(float_format=lambda v: f"{v:.3g}")
    print(with_pd_options)
    print(f"wrote {', '.join(files)} to {out}")


def cmd_compare(args) -> int:
    from pigp_torch.benchmark import run_benchmark
    from pigp_torch.ringargs import ring_spec_from_args

    ring = ring_spec_from_args(args)
    df = run_benchmark(
        args.methods,
        _seed_list(args.seeds),
        model_seed=args.model_seed,
        budgets={"gp": args.budget_gp, "direct": args.budget_direct},
        n_workers=args.workers,
        progress=True,
        ring=ring,
        scheduler=args.scheduler,
        center_ensemble=args.center_ensemble,
        machine_maps=not args.model_maps,
        prior_source=args.prior_source,
    )
    n_knobs = ring.build(args.model_seed).dim  # cached: the model ring was built already
    name = "spear3" if ring.is_spear3 else Path(ring.lattice).stem
    title = f"{name}-{n_knobs}, model seed {args.model_seed}"
    _write_comparison(df, args.out, title)
    return 0


# ----------------------------------------------------------------------------- demo
def _print_reports(reports) -> None:
    for r in reports:
        print(f"      held-out rel. RMSE {100 * r['val_rel_rmse']:.2f} %, "
              f"near optimum {100 * r['near_opt_rel_rmse']:.2f} %")  # fmt: skip


def cmd_demo(args) -> int:
    from pigp_torch.benchmark import METHODS, run_one
    from pigp_torch.prior import prior_from_model
    from pigp_torch.simulation import Spear3Coupling
    from pigp_torch.simulation.ensemble import ENSEMBLE_SEED0
    from pigp_torch.simulation.sampling import generate_dataset
    from pigp_torch.surrogate import train_ensemble

    if args.model_seed == args.machine_seed:
        raise ValueError("the model ring and the machine must have different error seeds")
    if args.center_ensemble < 0:
        raise ValueError(f"--center-ensemble must be >= 0, got {args.center_ensemble}")
    if args.center_ensemble and {args.model_seed, args.machine_seed} & set(
        range(ENSEMBLE_SEED0, ENSEMBLE_SEED0 + args.center_ensemble)
    ):
        raise ValueError(
            f"--center-ensemble {args.center_ensemble} uses error seeds {ENSEMBLE_SEED0}..."
            f"{ENSEMBLE_SEED0 + args.center_ensemble - 1}: choose model and machine seeds "
            "outside them"
        )
    unknown = [m for m in args.methods if m not in METHODS]
    if unknown:
        raise ValueError(f"unknown method(s) {unknown}; known: {sorted(METHODS)}")
    from pigp_torch.demo_cache import DemoCache, default_cache_dir, with_cached_ensemble

    out = args.out
    cache = None if args.no_cache else DemoCache(args.cache_dir or default_cache_dir())
    key = {"model_seed": args.model_seed, "n": args.n, "members": args.members,
           "target": args.target, "noise": 0.04, "sample_seed": 0}  # fmt: skip
    model_ring = Spear3Coupling(args.model_seed)
    hit = None if cache is None else cache.load_prior(key)
    if hit is not None:
        prior, reports = hit
        print(f"[1-3/4] physics prior of the surrogate from the cache ({cache.path('prior', key)}"
              "; --no-cache recomputes it)", flush=True)  # fmt: skip
        _print_reports(reports)
    else:
        print(f"[1/4] simulated data of the model ring (error seed {args.model_seed})", flush=True)
        data = generate_dataset(model_ring, args.n, seed=0, progress=True)
        print(f"[2/4] surrogate: {args.members} network(s) on {len(data)} samples", flush=True)
        surrogate, reports = train_ensemble(
            data, n_members=args.members, target=args.target, progress=True
        )
        _print_reports(reports)
        print("[3/4] physics prior: optimum and Hessian of the surrogate", flush=True)
        prior = prior_from_model(
            surrogate,
            model_ring.bounds,
            f_inf=model_ring.loss_background,
            noise=0.04,
            knob_names=model_ring.knob_names,
            provenance={"surrogate_of": f"Spear3Coupling(error_seed={args.model_seed})"},
        )
        if cache is not None:
            cache.save_prior(key, prior, reports)
    print(f"      condition number {prior.condition_number:.0f}, surrogate optimum "
          f"{prior.f_x0:.3f} mA/min")  # fmt: skip
    if args.center_ensemble and any(METHODS[m].uses_center_ensemble for m in args.methods):
        meta = {"error_seed": args.model_seed}

        def compute(p):
            return _with_center_ensemble(p, args.center_ensemble, meta, args.machine_seed)

        prior, source = with_cached_ensemble(
            prior, args.center_ensemble, args.model_seed, cache, compute
        )
        if source is not None:
            print(f"      optima of {args.center_ensemble} ensemble rings from the cache "
                  f"({source})", flush=True)  # fmt: skip
    print(f"[4/4] {', '.join(args.methods)} on machine error seed {args.machine_seed}, "
          f"{args.budget} evaluations each", flush=True)  # fmt: skip
    import pandas as pd

    from pigp_torch.progress import reporting_spec

    names, unit = model_ring.knob_names, model_ring.knob_units
    runs = [
        run_one(reporting_spec(METHODS[m], args.budget, names, unit=unit), args.machine_seed,
                prior, budget=args.budget)
        for m in args.methods
    ]  # fmt: skip
    df = pd.concat(runs, ignore_index=True)
    out.mkdir(parents=True, exist_ok=True)
    prior.save(out / "prior.json")
    _write_comparison(df, out, f"demo: machine seed {args.machine_seed}")
    return 0


# ----------------------------------------------------------------------------- bench
def cmd_bench_simulator(args) -> int:
    from pigp_torch.simulation.throughput import measure_throughput

    sim = _simulator(args)
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


# ----------------------------------------------------------------------------- parser
#: Modules of ``pigp_torch.commands`` that register further sub-commands.
COMMAND_MODULES: tuple[str, ...] = ("optimize", "serve_sim", "bench_bo", "report")


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

    p = sub.add_parser(
        "train-surrogate",
        help="train the neural-network surrogate on a dataset",
        description="Train an ensemble of smooth MLPs on a dataset NPZ (validation split, early "
        "stopping), save it without pickles, and report held-out errors.",
    )
    add_train_arguments(p)
    p.set_defaults(func=cmd_train_surrogate)

    p = sub.add_parser(
        "build-prior",
        help="physics prior (precision matrix) from a trained surrogate",
        description="Find the surrogate's optimum, take the autograd Hessian H of "
        "log(f - f_inf) there and write the prior (precision -H/2, amplitude, noise) as JSON.",
    )
    p.add_argument("model", type=Path, help="surrogate file from `pigp train-surrogate`")
    p.add_argument("-o", "--output", type=Path, required=True, help="prior file to write (.json)")
    p.add_argument("--noise", type=float, default=0.04, help="objective noise σ (mA/min)")
    p.add_argument(
        "--knob-limit",
        type=float,
        default=None,
        help="search the optimum within ±this (knob units, e.g. A) instead of the surrogate's "
        "bounds",
    )
    p.add_argument("--starts", type=int, default=16, help="multi-start count (default 16)")
    p.add_argument("--seed", type=int, default=0, help="seed of the starts")
    p.add_argument(
        "--center-ensemble",
        type=int,
        default=0,
        metavar="N",
        help="also store the covariance of the optimum and the mean shape of the peak over N "
        "simulated rings with other error seeds (1001...; same knobs and optics as the "
        "surrogate's data; ~3-7 s a ring); pigp-physics uses them as its prior on the machine's "
        "optimum and as the shape of its physics form (default 0: none)",
    )
    p.set_defaults(func=cmd_build_prior)

    p = sub.add_parser(
        "compare",
        help="benchmark optimizers on simulated machines (spear3-13 protocol)",
        description="Run methods x machine error seeds from skews zero with 0.04 mA/min noise, "
        "the physics prior computed from a different model ring; score every evaluation on the "
        "noise-free loss rate; write runs.csv, summary.csv and Fig. 2b/2c-style figures.",
    )
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
    from pigp_torch.ringargs import add_ring_arguments

    add_ring_arguments(p)
    p.add_argument(
        "--center-ensemble",
        type=int,
        default=40,
        metavar="N",
        help="model rings (error seeds 1001...) whose optima give pigp-physics its prior on "
        "where the machine's optimum lies and the mean shape of the peak (~3-7 s a ring; 0: "
        "box prior and the model ring's shape; default 40)",
    )
    p.add_argument("-o", "--out", type=Path, default=Path("runs/compare"), help="output folder")
    p.set_defaults(func=cmd_compare)

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
        default=_train_default("target"),
        help="surrogate target (default inv_sq_excess; log_excess is safer with little data)",
    )
    p.add_argument(
        "--center-ensemble",
        type=int,
        default=20,
        metavar="N",
        help="simulated rings whose optima give pigp-physics its prior on where the machine's "
        "optimum lies and the mean shape of the peak (~3-7 s a ring; 0: none; default 20)",
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
    p.add_argument("-o", "--out", type=Path, default=Path("runs/demo"), help="output folder")
    p.set_defaults(func=cmd_demo)

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
    b.add_argument(
        "--threads", type=int, default=None, help="CPU worker threads (default: torch's count)"
    )
    b.add_argument("--json", action="store_true", help="print one JSON object")
    b.set_defaults(func=cmd_bench_simulator)

    # Commands that live in their own modules (pigp_torch/commands/<name>.py), each with
    # ``register(sub, bench)`` adding its sub-parsers (cheap imports only at module level).
    import importlib

    for name in COMMAND_MODULES:
        importlib.import_module(f"pigp_torch.commands.{name}").register(sub, bench)
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (ValueError, FileNotFoundError, ConnectionError) as err:
        print(f"pigp {args.command}: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
