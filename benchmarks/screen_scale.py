r"""Screen of pigp-physics prior-check variants on the mismatch cases (tuning machines only).

Usage: ``python benchmarks/screen_scale.py VARIANTS CASES SEEDS BUDGET OUT`` with VARIANTS and
CASES comma-separated (variant names: the keys of ``V`` below), SEEDS ``a-b`` (>= 101), BUDGET
evaluations per run; prints one row per run (gain after 20 and 40, evaluation of the first prior
notice or -1) and the medians, and writes them to OUT (CSV).
"""

import sys
import time

import pandas as pd

from pigp_torch.benchmark.mismatch import cases
from pigp_torch.benchmark.protocol import run_one
from pigp_torch.methods.registry import METHODS
from pigp_torch.prior import PhysicsPrior
from pigp_torch.simulation import Spear3Coupling

S2 = {"shape_std": 1.0, "center_cov_scale_factor": 4.0}
V = {
    "D": {},
    "W": {
        "log_beta_std": 1.0,
        "f_inf_std": 0.1,
        "relax": [
            {"log_beta_std": 3.0, "f_inf_std": 0.1},
            {"log_beta_std": 3.0, "f_inf_std": 0.1, **S2},
        ],
    },
    "R": {
        "evidence_margin": 1.5,
        "relax": [
            {"log_beta_std": 3.0, "f_inf_std": 0.1},
            {"log_beta_std": 3.0, "f_inf_std": 0.1, **S2},
        ],
    },
    "R3": {
        "evidence_margin": 1.0,
        "relax": [
            {"log_beta_std": 3.0, "f_inf_std": 0.1},
            {"log_beta_std": 3.0, "f_inf_std": 0.1, **S2},
        ],
    },
    "Rb": {
        "evidence_margin": 1.5,
        "relax": [
            {"log_beta_std": 3.0},
            {"log_beta_std": 3.0, "f_inf_std": 0.1},
            {"log_beta_std": 3.0, "f_inf_std": 0.1, **S2},
        ],
    },
    "RE": {
        "evidence_margin": 1.5,
        "evidence_from": 10,
        "relax": [
            {"log_beta_std": 3.0, "f_inf_std": 0.1},
            {"log_beta_std": 3.0, "f_inf_std": 0.1, **S2},
        ],
    },
    "W1": {
        "log_beta_std": 1.0,
        "f_inf_std": 0.1,
        "relax": [{"log_beta_std": 1.0, "f_inf_std": 0.1, **S2}],
    },
}
variants = sys.argv[1].split(",")
cnames = sys.argv[2].split(",")
a, b = map(int, sys.argv[3].split("-"))
budget = int(sys.argv[4])
out = sys.argv[5]
if a <= 24:
    raise SystemExit("tune on machines outside the benchmark seeds 1-24 (use 101 and up)")
base = PhysicsPrior.load("docs/data/prior_spear3_seed0_surrogate.json")
half = (Spear3Coupling(1).bounds[1] - Spear3Coupling(1).bounds[0]) / 2
bycase = {c.name: c for c in cases(lambda **k: None, half)}
rows = []
for cn in cnames:
    case = bycase[cn]
    prior = case.prior(base)
    extra = case.options(prior)
    for v in variants:
        spec = METHODS["pigp-physics"].with_options(name="pigp-physics", **{**V[v], **extra})
        for s in range(a, b + 1):
            t0 = time.time()
            t = run_one(spec, s, prior, budget=budget, machine_maps=case.machine_maps)
            g = t.gain_fraction.values
            moved = (
                t.step[t.notice.astype(str).str.len() > 0].min()
                if (t.notice.astype(str).str.len() > 0).any()
                else -1
            )
            rows.append(
                dict(
                    case=cn,
                    variant=v,
                    seed=s,
                    g20=g[19],
                    g40=g[min(39, len(g) - 1)],
                    gend=g[-1],
                    moved=moved,
                    ms=1000 * t.ask_time_s.median(),
                    wall=time.time() - t0,
                )
            )
            print(rows[-1], flush=True)
            pd.DataFrame(rows).to_csv(out, index=False)
d = pd.DataFrame(rows)
print(d.groupby(["case", "variant"])[["g20", "g40", "gend"]].median())
