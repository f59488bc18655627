r"""PI-GP vs ML-II with all 72 skew windings as knobs.

Does the physics prior's advantage grow with dimension? The "spear3-13" protocol
(:mod:`pigp_torch.bench.protocol`) at ``knobs="all72"``: machines ``Spear3Coupling(s,
knobs="all72")`` for the machine seeds, the prior from the model ring (``model_seed``, same 72
knobs), both methods with their registry defaults (UCB β = 4, trust box ±0.3 of the normalized
range, ML-II on a 300-reading archive, refitted every step), every run from skews off with
0.04 mA/min noise, scored on the noise-free loss rate.

Two things differ from 13 knobs (see ``check``), and the study makes them explicit:

* The protocol's prior (:func:`~pigp_torch.bench.model_prior`, 16 Sobol starts searched as
  one L-BFGS-B problem) can fail at 72 knobs: for model seed 0 its x0 has a LOWER loss rate than
  skews off. ``--priors sobol zero`` runs PI-GP with that prior (``pigp``) and with the prior
  expanded at the optimum found from skews off (``pigp-x0zero``; same run seed as ``pigp``, so
  the pair differs only in the prior).
* ML-II refitted at every ask costs seconds of CPU per ask at 72 knobs (74 hyperparameters on
  300+ points); ``--ml2-refit-every 10`` refits every 10th ask (warm start; same archive and run
  seed as ``ml2``), labelled ``ml2-refit10``.
* The machines' f* is expensive (minutes a seed) and start-dependent at 72 knobs, so
  ``--optimum-starts 0`` skips it: runs are then scored by the absolute gain
  ``best_f_true - f0`` (mA/min) after n evaluations instead of the fraction of f* - f0.

Usage::

    # what the problem looks like: f0, f* from Sobol starts / from skews off / with 2x bounds,
    # knobs at a bound, and the wall and CPU time of one run of each method
    python benchmarks/knobs72.py check --knobs all72 --seeds 1 --budget 20

    # the study (results appended per seed to OUT/runs_<knobs>_b<budget>.csv; a re-run resumes)
    nice -n 10 python benchmarks/knobs72.py run --knobs all72 --seeds 1-8 --budget 60 \
        --optimum-starts 0 --priors sobol zero --ml2-refit-every 10 --workers 3 \
        --out /work/notes/knobs72
    nice -n 10 python benchmarks/knobs72.py run --knobs paper13 --seeds 1-8 --budget 60 \
        --priors sobol zero --workers 3 --out /work/notes/knobs72

    # the table again from the CSVs
    python benchmarks/knobs72.py table --knobs all72 paper13 --budget 60 --out /work/notes/knobs72

Runs are seeded per (method, machine seed) (the protocol's :func:`~pigp_torch.bench.run_one`),
so a resumed or parallel (``--workers``) study gives the same numbers as an uninterrupted serial
one; a run's first n evaluations do not depend on its budget (BayesOpt seeds ask k with
``seed + k``), so the gain after n < budget is that of a run with budget n.
"""

from __future__ import annotations

import argparse
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from pigp_torch.bench import METHODS, NOISE, machine_optimum, model_prior, run_one, summarize
from pigp_torch.prior import PhysicsPrior, find_optimum, prior_from_model
from pigp_torch.simulation import Spear3Coupling

OPTIMUM_STARTS = 8
#: (label in the table, registry method, prior) for ``--priors sobol`` / ``zero``.
VARIANTS = {
    "sobol": [("pigp", "pigp"), ("ml2", "ml2")],
    "zero": [("pigp-x0zero", "pigp")],
}


def seed_list(text: str) -> list[int]:
    """``"1-8"``, ``"1,3,5"`` or ``"1-4,9"`` -> list of ints (the ``pigp compare`` syntax)."""
    from pigp_torch.cli import _seed_list

    return _seed_list(text)


def zeros(sim: Spear3Coupling) -> torch.Tensor:
    return torch.zeros(sim.dim, dtype=torch.float64)


def prior_path(out: Path, knobs: str, model_seed: int, start: str) -> Path:
    return out / f"prior_{knobs}_model{model_seed}_{start}.json"


def prior_for(knobs: str, model_seed: int, out: Path, start: str) -> PhysicsPrior:
    """The model ring's prior, cached as JSON in ``out`` (plain data).

    ``start="sobol"``: the protocol's :func:`~pigp_torch.bench.model_prior` (16 Sobol
    starts). ``"zero"``: x0 = the maximum found by L-BFGS-B from skews off (one start).
    """
    path = prior_path(out, knobs, model_seed, start)
    if path.exists():
        return PhysicsPrior.load(path)
    torch.set_num_threads(1)
    t = time.perf_counter()
    if start == "sobol":
        prior = model_prior(model_seed, knobs=knobs)
    elif start == "zero":
        sim = Spear3Coupling(model_seed, knobs=knobs)
        x0, _ = find_optimum(sim.loss_rate, sim.bounds, n_starts=0, x_init=zeros(sim))
        prior = prior_from_model(
            sim.loss_rate,
            sim.bounds,
            f_inf=sim.loss_background,
            noise=NOISE,
            x0=x0,
            knob_names=sim.knob_names,
            provenance={
                "model": f"Spear3Coupling(error_seed={model_seed}, knobs={knobs!r})",
                "x0": "L-BFGS-B from skews off",
            },
        )
    else:
        raise ValueError(f"prior start must be 'sobol' or 'zero', got {start!r}")
    at_bound = int((prior.x0.abs() > 0.999 * prior.bounds[1]).sum())
    print(f"[{knobs}] prior ({start}) from model seed {model_seed}: {time.perf_counter() - t:.0f}"
          f" s, f(x0) {prior.f_x0:.3f} mA/min, {at_bound} knobs at a bound, condition number "
          f"{prior.condition_number:.3g}", flush=True)  # fmt: skip
    out.mkdir(parents=True, exist_ok=True)
    partial = path.with_suffix(".partial.json")
    prior.save(partial)
    partial.replace(path)  # atomic: other processes wait for the file to exist
    return prior


def cmd_check(args) -> int:
    """f0; f* from Sobol starts, from skews off and with doubled bounds; knobs at a bound; the
    wall and CPU time of one run of each method."""
    rows = []
    for knobs in args.knobs:
        for seed in seed_list(args.seeds):
            sim = Spear3Coupling(seed, knobs=knobs)
            f0 = float(sim.loss_rate(zeros(sim)))
            t = time.perf_counter()
            x_star, f_star = sim.optimum(n_starts=OPTIMUM_STARTS)  # = machine_optimum's search
            t_opt = time.perf_counter() - t
            x_zero, f_zero = find_optimum(sim.loss_rate, sim.bounds, n_starts=0, x_init=zeros(sim))
            wide = Spear3Coupling(seed, knobs=knobs, knob_limit=2 * sim.knob_limit)
            _, f_wide = wide.optimum(n_starts=OPTIMUM_STARTS)
            lim = 0.999 * sim.knob_limit
            rows.append(
                {
                    "knobs": knobs,
                    "seed": seed,
                    "f0": f0,
                    "f_star_sobol": f_star,
                    "at_bound_sobol": int((x_star.abs() > lim).sum()),
                    "eps_ratio_sobol": float(
                        sim.evaluate(x_star).eps_y / sim.evaluate(x_star).eps_x
                    ),
                    "f_star_from_zero": f_zero,
                    "at_bound_zero": int((x_zero.abs() > lim).sum()),
                    "f_star_sobol_2x_bounds": f_wide,
                    "sobol_search_s": t_opt,
                }
            )
            print(pd.DataFrame(rows[-1:]).to_string(index=False, float_format="%.4g"), flush=True)
    print(pd.DataFrame(rows).to_string(index=False, float_format="%.4g"))
    if args.budget > 0:
        out = Path(args.out)
        for knobs in args.knobs:
            prior = prior_for(knobs, args.model_seed, out, "sobol")
            seed = seed_list(args.seeds)[0]
            for name in ("pigp", "ml2"):
                t, c = time.perf_counter(), time.process_time()
                table = run_one(
                    METHODS[name], seed, prior, budget=args.budget, knobs=knobs, optimum_starts=0
                )
                wall, cpu = time.perf_counter() - t, time.process_time() - c
                ask = table["ask_time_s"].to_numpy()
                print(f"[{knobs}] {name} seed {seed}, {args.budget} evaluations: wall {wall:.0f} s,"
                      f" CPU {cpu:.0f} s (last 5 asks {ask[-5:].mean():.2f} s wall each)",
                      flush=True)  # fmt: skip
    return 0


def runs_path(out: Path, knobs: str, budget: int) -> Path:
    return out / f"runs_{knobs}_b{budget}.csv"


def seed_job(job) -> pd.DataFrame:
    """Every variant on one machine seed in this process, so f* is searched at most once.

    The f* search (if any) runs first, while other processes may still compute the priors; the
    priors are then read from their JSON files (waited for, bounded).
    """
    seed, variants, knobs, budget, priors, optimum_starts, ml2_refit_every, wait_s = job
    torch.set_num_threads(1)
    if optimum_starts > 0:
        machine_optimum(seed, optimum_starts, knobs=knobs)
    deadline = time.monotonic() + wait_s
    while not all(p.exists() for p in priors.values()):
        if time.monotonic() > deadline:
            raise TimeoutError(f"priors {list(priors.values())} missing after {wait_s} s")
        time.sleep(5.0)
    tables = []
    for label, method, start in variants:
        prior = PhysicsPrior.load(priors[start])
        spec = METHODS[method]
        if method == "ml2" and ml2_refit_every != 1:  # same name: same run seed and archive
            spec = spec.with_options(refit_every=ml2_refit_every)
        t, c = time.perf_counter(), time.process_time()
        table = run_one(
            spec,
            seed,
            prior,
            budget=budget,
            knobs=knobs,
            optimum_starts=optimum_starts,
        )
        table["method"] = label  # pigp-x0zero keeps pigp's run seed: a paired comparison
        tables.append(table)
        print(f"[{knobs}] {label} seed {seed}: {budget} evaluations, wall "
              f"{time.perf_counter() - t:.0f} s, CPU {time.process_time() - c:.0f} s",
              flush=True)  # fmt: skip
    df = pd.concat(tables, ignore_index=True)
    df.insert(0, "knobs", knobs)
    return df


def cmd_run(args) -> int:
    """Run the grid, one process task per machine seed, appending each seed's runs to the CSV as
    it finishes (a re-run skips the (method, seed) pairs already there)."""
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    ml2_label = "ml2" if args.ml2_refit_every == 1 else f"ml2-refit{args.ml2_refit_every}"
    variants = [
        (ml2_label if label == "ml2" else label, method, start)
        for start in args.priors
        for label, method in VARIANTS[start]
    ]
    for knobs in args.knobs:
        priors = {st: prior_path(out, knobs, args.model_seed, st) for st in args.priors}
        path = runs_path(out, knobs, args.budget)
        done = set()
        if path.exists():
            old = pd.read_csv(path, usecols=["method", "machine_seed"])
            done = set(old.itertuples(index=False, name=None))
        jobs = []
        for seed in seed_list(args.seeds):
            if seed == args.model_seed:
                raise ValueError(f"machine seed {seed} is the model seed")
            todo = [v for v in variants if (v[0], seed) not in done]
            if todo:
                jobs.append(
                    (seed, todo, knobs, args.budget, priors, args.optimum_starts,
                     args.ml2_refit_every, 7200.0)
                )  # fmt: skip
        if not jobs:
            continue
        print(f"[{knobs}] {len(jobs)} machine seeds to run on {args.workers} process(es)")
        with ProcessPoolExecutor(max_workers=args.workers) as pool:
            pending = [
                pool.submit(prior_for, knobs, args.model_seed, out, st)
                for st, p in priors.items()
                if not p.exists()
            ]
            pending += [pool.submit(seed_job, job) for job in jobs]
            for future in as_completed(pending):
                result = future.result()
                if isinstance(result, pd.DataFrame):
                    result.to_csv(path, mode="a", header=not path.exists(), index=False)
                    print(f"[{knobs}] seed {result['machine_seed'].iloc[0]} written", flush=True)
    return cmd_table(args)


def absolute_gains(df: pd.DataFrame, at) -> pd.DataFrame:
    """Per run: best noise-free loss rate so far minus f0 (mA/min) after each n in ``at``."""
    rows = []
    for (method, seed), run in df.groupby(["method", "machine_seed"], sort=False):
        run = run.sort_values("step")
        best = run["best_f_true"].to_numpy()
        row = {"method": method, "machine_seed": seed, "f0": float(run["f0"].iloc[0])}
        for n in at:
            row[f"dfbest_{n}"] = float(best[n - 1] - row["f0"]) if len(best) >= n else np.nan
        rows.append(row)
    return pd.DataFrame(rows)


def cmd_table(args) -> int:
    """Median [q25, q75] over seeds: absolute gain best_f_true - f0 (mA/min) after 40 and
    ``budget`` evaluations; where f* is known also the gain fraction and steps-to-95."""
    out = Path(args.out)
    at = (40, args.budget)
    lines = [
        f"| knobs | method | runs | gain@40 (mA/min) | gain@{args.budget} (mA/min) | "
        f"fraction@40 | fraction@{args.budget} | reached 95 % | steps-to-95 |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    parts = []

    def cell(v) -> str:
        v = pd.Series(v).dropna()
        if v.empty:
            return "n/a"
        q = v.quantile([0.25, 0.5, 0.75]).to_numpy()
        return f"{q[1]:.3g} [{q[0]:.3g}, {q[2]:.3g}]"

    for knobs in args.knobs:
        path = runs_path(out, knobs, args.budget)
        if not path.exists():
            print(f"no runs for {knobs} at budget {args.budget} ({path})")
            continue
        df = pd.read_csv(path)
        gains = absolute_gains(df, at)
        summary = summarize(df, at=at)
        for method, g in gains.groupby("method", sort=False):
            s = summary.loc[method]
            known = bool(df.loc[df["method"] == method, "f_star"].notna().all())
            rows = [df[(df["method"] == method) & (df["step"] == n - 1)] for n in at]
            frac = [cell(r["gain_fraction"]) for r in rows]
            steps, reached = "n/a", "n/a"
            if known:
                steps = (
                    f"{s['steps_to_95_median']:.3g} [{s['steps_to_95_q25']:.3g}, "
                    f"{s['steps_to_95_q75']:.3g}]"
                )
                reached = str(int(s["n_reached_95"]))
            dfb = cell(g[f"dfbest_{args.budget}"])
            lines.append(
                f"| {knobs} | {method} | {len(g)} | {cell(g['dfbest_40'])} | {dfb} | "
                f"{frac[0]} | {frac[1]} | {reached} | {steps} |"
            )
            parts.append(g.assign(knobs=knobs))
    if not parts:
        return 1
    pd.concat(parts, ignore_index=True).to_csv(out / f"gains_b{args.budget}.csv", index=False)
    table = "\n".join(lines)
    (out / f"summary_b{args.budget}.md").write_text(table + "\n")
    print("median [q25, q75] over machine seeds; gain = best noise-free loss rate so far - f0")
    print(table)
    return 0


def main(argv=None) -> int:
    torch.set_num_threads(1)
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="cmd", required=True)
    for name, func, help_ in (
        ("check", cmd_check, "f*, bounds and timing of one run per method"),
        ("run", cmd_run, "run the study (resumable) and print the table"),
        ("table", cmd_table, "print the table from the CSVs"),
    ):
        p = sub.add_parser(name, help=help_, description=help_)
        p.add_argument("--knobs", nargs="+", default=["all72"], help="knob sets (all72 paper13)")
        p.add_argument("--seeds", default="1-8", help="machine seeds, e.g. 1-8")
        p.add_argument("--model-seed", type=int, default=0, help="model ring of the prior")
        p.add_argument("--budget", type=int, default=100, help="evaluations per run")
        p.add_argument(
            "--priors",
            nargs="+",
            default=["sobol"],
            choices=sorted(VARIANTS),
            help="sobol: pigp and ml2 with the protocol's prior; zero: pigp-x0zero",
        )
        p.add_argument(
            "--optimum-starts",
            type=int,
            default=OPTIMUM_STARTS,
            help="Sobol starts of each machine's f* search (0: none, absolute gains only)",
        )
        p.add_argument(
            "--ml2-refit-every",
            type=int,
            default=1,
            help="ML-II hyperparameter refit period in asks (protocol: 1; labelled ml2-refit<N>)",
        )
        p.add_argument("--workers", type=int, default=1, help="processes (one seed each)")
        p.add_argument("-o", "--out", type=Path, default=Path("runs/knobs72"), help="folder")
        p.set_defaults(func=func)
    args = parser.parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
