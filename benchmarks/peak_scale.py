r"""How far each machine's peak is from what the prior of ``pigp-physics`` expects.

``pigp-physics`` fits :math:`f = f_\infty + (c + \beta(\mathbf x - \boldsymbol\mu)^\top B
(\mathbf x - \boldsymbol\mu))^{-1/2}` with the shape :math:`B` of the prior (the ensemble's mean
peak shape), a prior on :math:`\log\beta` around 0 (std 0.3 in the given model) and one on
:math:`\log c` around the model ring's :math:`\log c_m` (std 1.5), and the prior's background.
For each machine this script takes its own peak (:func:`~pigp_torch.bench.oracle
.machine_peak`: centre :math:`\boldsymbol\mu`, shape :math:`B_s` normalized to
:math:`\beta = 1`, :math:`c_s = (f(\boldsymbol\mu) - f_\infty)^{-2}`) and prints

* ``beta_min``, ``beta_med``, ``beta_max``: the generalized eigenvalues of :math:`B_s` against
  the prior's :math:`B` (least, median, largest): the :math:`\beta` the fit must find along
  each eigen-direction with the prior's shape (1 = the prior's scale);
* ``log_beta``: :math:`\log` of ``beta_med``, in units of the given model's prior std (0.3);
* ``c_ratio``: :math:`c_s / c_m` (the peak height above background, :math:`c^{-1/2}`, relative to
  the model ring's);
* ``width``: the median generalized eigenvalue of :math:`B_s/c_s` against :math:`B/c_m`
  (> 1: a narrower peak in knob space than the model ring's), and ``f_inf`` against the prior's.

    python benchmarks/peak_scale.py --family wide --seeds 101-112 -o runs/peak_scale_wide.csv
"""

from __future__ import annotations

import argparse
import math
import os
import sys

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import pandas as pd
import scipy.linalg
import torch

from pigp_torch.bench.families import FAMILIES
from pigp_torch.bench.machines import benchmark_ring
from pigp_torch.bench.oracle import machine_peak
from pigp_torch.commands.compare import seed_list
from pigp_torch.prior import PhysicsPrior
from pigp_torch.simulation.spec import SPEAR3

PRIOR = "docs/data/prior_spear3_seed0_surrogate.json"
#: the given model's prior std of log beta (InverseSqrtPeakModel's default)
LOG_BETA_STD = 0.3


def generalized_eigenvalues(A: torch.Tensor, B: torch.Tensor) -> torch.Tensor:
    """Eigenvalues :math:`\\lambda` of :math:`A\\mathbf v = \\lambda B\\mathbf v` (``B``
    positive definite), ascending (LAPACK's generalized symmetric solver through SciPy)."""
    lam = scipy.linalg.eigh(A.numpy(), B.numpy(), eigvals_only=True)
    return torch.from_numpy(lam)


def machine_row(prior: PhysicsPrior, seed: int, family: str) -> dict:
    """One row of the table (module docstring) for machine ``seed`` of ``family``."""
    sim = benchmark_ring(seed, SPEAR3, True, family=family)
    mu, B_s = machine_peak(sim)
    f_inf = float(sim.loss_background)
    c_s = (float(sim.loss_rate(mu)) - f_inf) ** -2
    c_m = (float(prior.f_x0) - float(prior.f_inf)) ** -2
    B = prior.peak_shape if prior.peak_shape is not None else 2 * c_m * prior.precision
    beta = generalized_eigenvalues(B_s, B)
    width = generalized_eigenvalues(B_s / c_s, B / c_m)
    return {
        "family": family,
        "machine_seed": int(seed),
        "beta_min": float(beta[0]),
        "beta_med": float(beta.median()),
        "beta_max": float(beta[-1]),
        "log_beta": math.log(float(beta.median())) / LOG_BETA_STD,
        "c_ratio": c_s / c_m,
        "width": float(width.median()),
        "f_inf": f_inf,
        "f_inf_prior": float(prior.f_inf),
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--family", choices=FAMILIES, default="project")
    p.add_argument("--seeds", default="101-112", help="machine seeds (e.g. 101-112 or 1-24)")
    p.add_argument("--prior", default=PRIOR, help=f"prior JSON (default {PRIOR})")
    p.add_argument("-o", "--out", help="also write the table to this CSV")
    args = p.parse_args(argv)
    prior = PhysicsPrior.load(args.prior)
    rows = []
    for seed in seed_list(args.seeds):
        rows.append(machine_row(prior, seed, args.family))
        print(f"machine {seed}: beta median {rows[-1]['beta_med']:.2f}", file=sys.stderr)
    df = pd.DataFrame(rows)
    with pd.option_context("display.width", 200):
        print(df.round(3).to_string(index=False))
    q = df[["beta_med", "c_ratio", "width", "f_inf"]].quantile([0.0, 0.5, 1.0])
    print("min / median / max:\n" + q.round(3).to_string())
    if args.out:
        df.to_csv(args.out, index=False)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
