r"""Screen of pigp-physics prior-check variants on mismatch cases (tuning machines only).

``python benchmarks/screen_scale.py --variants D R RE --cases scale×10 control --seeds 101-104
--budget 40 -o runs/screen_scale.csv``: one run per variant, case and machine (the kept prior
``docs/data/prior_spear3_seed0_surrogate.json``); prints each run's gain after 20 and 40
evaluations and the evaluation of its first prior notice, then the medians; writes the rows to
``-o`` after every run. Variant names are the keys of :data:`VARIANTS`; besides the suite's
cases, ``scale*F`` scales the prior's shape by any factor ``F`` (e.g. ``scale*2``).
"""

from __future__ import annotations

import argparse

import pandas as pd

from pigp_torch.benchmark.mismatch import Case, cases, scaled
from pigp_torch.benchmark.protocol import run_one
from pigp_torch.benchmark.scoring import run_scores
from pigp_torch.commands.compare import seed_list
from pigp_torch.methods.registry import METHODS
from pigp_torch.optimizers.physics_bo import relaxed_stages
from pigp_torch.prior import PhysicsPrior
from pigp_torch.simulation import Spear3Coupling

PRIOR = "docs/data/prior_spear3_seed0_surrogate.json"


def wide_stages(log_beta_std: float = 3.0, scale_only_first: bool = False) -> list[dict]:
    """The default stages of the prior check with a wider ``log_beta_std`` (optionally first a
    stage that frees only the scale)."""
    first = [{"log_beta_std": log_beta_std}] if scale_only_first else []
    return first + list(relaxed_stages(log_beta_std=log_beta_std))


#: name -> pigp-physics options (``{}``: the defaults).
VARIANTS = {
    "D": {},  # the defaults (since 2026-12-04 with the broader-shape stage, = H3)
    "D0": {"relax": list(relaxed_stages())},  # the defaults before it
    "B5": {"log_beta_std": 0.5},
    "W": {"log_beta_std": 1.0, "f_inf_std": 0.1, "relax": wide_stages()},
    "R": {"evidence_margin": 1.5, "relax": wide_stages()},
    "R3": {"evidence_margin": 1.0, "relax": wide_stages()},
    "Rb": {"evidence_margin": 1.5, "relax": wide_stages(scale_only_first=True)},
    "RE": {"evidence_margin": 1.5, "evidence_from": 10, "relax": wide_stages()},
    # scale hypotheses: the given shape x1/3 (and x3) with the given, tight scale prior, before
    # the wider stages (the same prior width, so no Occam cost against the given model)
    "H3": {"relax": [{"shape_factor": 1 / 3}, *relaxed_stages()]},
    "H33": {"relax": [{"shape_factor": 1 / 3}, {"shape_factor": 3.0}, *relaxed_stages()]},
}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--variants", nargs="+", default=["D"], choices=sorted(VARIANTS))
    p.add_argument("--cases", nargs="+", default=["control"])
    p.add_argument("--seeds", default="101-104", help="tuning machine seeds (>= 101)")
    p.add_argument("--budget", type=int, default=40)
    p.add_argument("-o", "--out", default="runs/screen_scale.csv")
    args = p.parse_args(argv)
    seeds = seed_list(args.seeds)
    if min(seeds) <= 24:
        raise SystemExit("tune on machines outside the benchmark seeds 1-24 (use 101 and up)")
    base = PhysicsPrior.load(PRIOR)
    bounds = Spear3Coupling(1).bounds
    by_name = {c.name: c for c in cases(lambda **k: None, (bounds[1] - bounds[0]) / 2)}
    for name in args.cases:  # other scales than the suite's: "scale*F" (F > 0, e.g. scale*2)
        if name not in by_name and name.startswith("scale*"):
            f = float(name.removeprefix("scale*"))
            by_name[name] = Case(name, lambda p, f=f: scaled(p, f))
    rows = []
    for name in args.cases:
        case = by_name[name]
        prior = case.prior(base)
        for variant in args.variants:
            options = {**VARIANTS[variant], **case.options(prior)}
            spec = METHODS["pigp-physics"].with_options(**options)  # same seeds as the table
            for seed in seeds:
                run = run_one(spec, seed, prior, budget=args.budget,
                              machine_maps=case.machine_maps)  # fmt: skip
                score = run_scores(run, at=(20, 40)).iloc[0]
                noticed = run.loc[run["notice"].astype(str) != "", "step"]
                rows.append({"case": name, "variant": variant, "seed": seed,
                             "gain_20": score["gain_20"], "gain_40": score["gain_40"],
                             "moved": int(noticed.min()) if len(noticed) else -1})  # fmt: skip
                print(rows[-1], flush=True)
                pd.DataFrame(rows).to_csv(args.out, index=False)
    print(pd.DataFrame(rows).groupby(["case", "variant"])[["gain_20", "gain_40"]].median())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
