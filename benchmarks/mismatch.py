"""The mismatch suite: pigp-physics given priors of a model the machines are not.

For each case of :mod:`pigp_torch.bench.mismatch` (a re-tuned model ring, the design deck,
a scaled or rotated shape, a shifted centre prior, a wrong calibration, machines with a
loss-rate map further off than the benchmark's spread) this runs ``pigp-physics`` (and any
variants given) on the spear3-13 machines, and the baselines (``--baselines``, default ``ml2``
and ``xopt-ucb``) where the case changes the machines (the loss-rate cases) or once on the
control machines (the prior does not reach them). Prints, per case and method, the median
(IQR) gain after 20 / 40 / 100 evaluations, machines at 95 % and the runs whose prior check
rejected the prior (with the median evaluation at which it did).

    python benchmarks/mismatch.py --prior runs/prior_surrogate.json --seeds 1-24 --workers 2 \\
        -o runs/mismatch.csv

Priors of re-tuned / design-deck model rings are exact-model priors with their own 40-ring
error ensemble, cached in ``--cache`` (about a minute each). Tune methods on seeds 101 and up.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import pandas as pd
from screen_physics import parse_variant  # the sibling script (benchmarks/ is on sys.path)

from pigp_torch.bench import METHODS, run_benchmark
from pigp_torch.bench.families import FAMILIES
from pigp_torch.bench.mismatch import cases
from pigp_torch.bench.protocol import ENSEMBLE_SIZE, model_prior
from pigp_torch.bench.scoring import first_moves, run_scores
from pigp_torch.commands.compare import seed_list
from pigp_torch.prior import PhysicsPrior
from pigp_torch.simulation import Spear3Coupling


def cached_prior(cache: Path, key: str, build) -> PhysicsPrior:
    path = cache / f"{key}.json"
    if path.exists():
        return PhysicsPrior.load(path)
    print(f"prior of the {key} model ring (exact, {ENSEMBLE_SIZE}-ring ensemble) ...", flush=True)
    prior = build()
    cache.mkdir(parents=True, exist_ok=True)
    prior.save(path)
    return prior


def table(df: pd.DataFrame) -> pd.DataFrame:
    """Per case and method: medians (IQR) of the gains, reached 95 %, prior rejections."""
    scores = pd.concat([run_scores(g).assign(case=c) for c, g in df.groupby("case", sort=False)])
    rows = []
    for (case, method), g in scores.groupby(["case", "method"], sort=False):
        row = {"case": case, "method": method, "runs": len(g),
               "reached_95": int(g["reached_95"].sum())}  # fmt: skip
        for k in (20, 40, 100):
            q = g[f"gain_{k}"].quantile([0.25, 0.5, 0.75])
            row[f"gain_{k}"] = f"{q.iloc[1]:.2f} ({q.iloc[0]:.2f}-{q.iloc[2]:.2f})"
        rej = first_moves(df[(df["case"] == case) & (df["method"] == method)])
        row["rejected"] = f"{len(rej)}/{len(g)}"
        row["rejected_at"] = float(rej.median()) if len(rej) else float("nan")
        rows.append(row)
    return pd.DataFrame(rows)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--prior", default=None, help="the benchmark's prior JSON (default: exact)")
    p.add_argument("--seeds", default="1-24", help="machine seeds (default 1-24)")
    p.add_argument(
        "--cases", nargs="*", default=None, help="case names, run in the order given (default: all)"
    )
    p.add_argument("--variants", nargs="*", default=["pigp-physics"],
                   help="pigp-physics variants: name or name=key=value,...")  # fmt: skip
    p.add_argument("--baselines", nargs="*", default=["ml2", "xopt-ucb"])
    p.add_argument("--workers", type=int, default=1)
    p.add_argument("--family", choices=FAMILIES, default="project",
                   help="machine family (default project); the wide family runs only the cases "
                   "that keep the machines' own loss-rate maps")  # fmt: skip
    p.add_argument("--cache", default="runs/mismatch_priors", help="folder of built priors")
    p.add_argument("-o", "--out", default="runs/mismatch.csv")
    args = p.parse_args(argv)
    seeds = seed_list(args.seeds)
    cache = Path(args.cache)
    if args.prior:
        base = PhysicsPrior.load(args.prior)
    else:
        base = cached_prior(cache, "exact-user",
                            lambda: model_prior(0, center_ensemble=ENSEMBLE_SIZE))  # fmt: skip

    def model_prior_of(model=None, optics="user"):
        if model is not None:
            key = model.name.replace(" ", "_").replace("=", "")
            return cached_prior(cache, key, lambda: model_prior(0, center_ensemble=ENSEMBLE_SIZE,
                                                                 model=model))  # fmt: skip
        from pigp_torch.simulation.spec import RingSpec

        return cached_prior(cache, f"exact-{optics}", lambda: model_prior(
            0, center_ensemble=ENSEMBLE_SIZE, ring=RingSpec(optics=optics)))  # fmt: skip

    sim = Spear3Coupling(1)
    half = (sim.bounds[1] - sim.bounds[0]) / 2
    suite = cases(model_prior_of, half)
    if args.cases:
        unknown = set(args.cases) - {c.name for c in suite}
        if unknown:
            raise SystemExit(f"unknown cases {sorted(unknown)}; known: {[c.name for c in suite]}")
        by_name = {c.name: c for c in suite}
        suite = [by_name[n] for n in dict.fromkeys(args.cases)]  # in the order given
    if args.family == "wide":  # a wide machine draws its own map: no loss-map cases
        suite = [c for c in suite if c.machine_maps is True]
    variants = [parse_variant(v) for v in args.variants]
    frames = []
    for case in suite:
        prior = case.prior(base)
        extra = case.options(prior)
        specs = [METHODS["pigp-physics"].with_options(name=name, **{**opts, **extra})
                 for name, opts in variants]  # fmt: skip
        if case.name == "control" or case.machine_maps is not True:
            specs += [METHODS[m] for m in args.baselines]
        print(f"case {case.name}: {[s.name for s in specs]} on {len(seeds)} machines", flush=True)
        df = run_benchmark(specs, seeds, prior=prior, n_workers=args.workers,
                           machine_maps=case.machine_maps, progress=False,
                           family=args.family)  # fmt: skip
        df.insert(0, "case", case.name)
        frames.append(df)
        pd.concat(frames).to_csv(args.out, index=False)
        with pd.option_context("display.width", 250, "display.max_columns", 20):
            print(table(df).to_string(index=False), flush=True)
    out = pd.concat(frames)
    print("\nall cases")
    with pd.option_context("display.width", 250, "display.max_columns", 20):
        print(table(out).to_string(index=False))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
