r"""Where a ``pigp-physics`` run loses evaluations: the fit, the final visit or the machine's form.

For each machine (benchmark family ``--family``, seeds ``--seeds``; tune on 101 and up) this
script

1. measures how far the machine is from the physics form around its own peak: along
   ``--directions`` random directions :math:`\mathbf v` of unit length in the metric of the
   machine's own shape :math:`B_s` (:func:`~pigp_torch.bench.oracle.machine_peak`), the
   ratio :math:`(g(\boldsymbol\mu + \sqrt q\,\mathbf v) - c)/q` with :math:`g = (f -
   f_\infty)^{-2}` (exactly 1 for the form, :func:`quadratic_departure`);
2. runs ``pigp-physics`` (``--oracle``: told the machine's own shape, height and background;
   ``--options``: JSON options) from skews zero with the benchmark's noise (its own noise
   draw, not a benchmark run's) and prints per evaluation the gain fraction of the best
   reading so far and that of the fitted form's box optimum (what a visit of the fitted
   optimum would score), and, with ``--oracle``, every ``--every`` readings the fit's negative
   log posterior, that of the true :math:`\theta` (the machine's peak) and that of a refit
   started from the truth (a lower value there would mean the fit missed its optimum).

    python benchmarks/fit_diagnosis.py --seeds 101-106 --oracle --budget 50
"""

from __future__ import annotations

import argparse
import copy
import json
import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np
import torch

from pigp_torch._utils import DTYPE
from pigp_torch._utils.lbfgsb import minimize_lbfgsb
from pigp_torch.bench.families import FAMILIES
from pigp_torch.bench.machines import benchmark_ring, machine_optimum
from pigp_torch.bench.oracle import machine_peak, oracle_prior
from pigp_torch.bench.protocol import NOISE
from pigp_torch.commands.compare import seed_list
from pigp_torch.machine import SimulatedMachine
from pigp_torch.methods import RunContext
from pigp_torch.models._inverse_sqrt_fit import _NumpyObjective
from pigp_torch.optimizers.physics_bo import PhysicsModelBO
from pigp_torch.prior import PhysicsPrior
from pigp_torch.simulation.spec import SPEAR3

PRIOR = "docs/data/prior_spear3_seed0_surrogate.json"


def quadratic_departure(loss_rate, f_inf: float, mu, B, qs, n_dirs: int, seed: int = 0):
    r"""``n_dirs x len(qs)`` ratios :math:`(g(\boldsymbol\mu + \sqrt q\,\mathbf v) - c)/q`,
    :math:`g = (f - f_\infty)^{-2}`, :math:`c = g(\boldsymbol\mu)`, along random directions
    :math:`\mathbf v` with :math:`\mathbf v^\top B\mathbf v = 1` (``loss_rate``: ``d`` ->
    scalar tensor; ``mu``: ``d``; ``B``: ``d x d``). 1 everywhere for the exact form
    :math:`f_\infty + (c + (\mathbf x - \boldsymbol\mu)^\top B(\mathbf x -
    \boldsymbol\mu))^{-1/2}`."""
    g = torch.Generator().manual_seed(seed)
    c = (float(loss_rate(mu)) - f_inf) ** -2
    out = np.empty((n_dirs, len(qs)))
    for i in range(n_dirs):
        v = torch.randn(mu.shape[0], generator=g, dtype=DTYPE)
        v = v / torch.sqrt(v @ B @ v)
        for j, q in enumerate(qs):
            out[i, j] = ((float(loss_rate(mu + v * q**0.5)) - f_inf) ** -2 - c) / q
    return out


def trace_run(prior, sim, seed: int, budget: int, oracle: bool, every: int, options: dict,
              family: str) -> None:  # fmt: skip
    """Print the per-evaluation trace of one run (module docstring, item 2)."""
    f_star = machine_optimum(seed, 8, machine_maps=True, family=family)
    machine = SimulatedMachine(sim, noise=NOISE, seed=seed)
    ctx = RunContext(machine=machine, prior=prior, seed=seed, noise=NOISE)
    if oracle:
        prior = oracle_prior(ctx)
        mu_true, _ = machine_peak(sim)
    opt = PhysicsModelBO(sim.bounds, prior, seed=seed, noise=NOISE, **options)
    x = torch.zeros(sim.dim, dtype=DTYPE)
    f0 = float(sim.loss_rate(x))
    best = f0
    print(f"machine {seed}: f0 {f0:.3f} f* {f_star:.3f} mA/min")
    print("    n  gain(best reading)  gain(fitted optimum)  inform" +
          ("  nlp(fit)  nlp(truth)  nlp(refit from truth)" if oracle else ""))  # fmt: skip
    for n in range(budget):
        machine.set(x)
        y = float(machine.read())
        best = max(best, float(sim.loss_rate(x)))
        opt.tell(x, y)
        line = f"{n:5d}  {(best - f0) / (f_star - f0):18.3f}"
        if n > 0:
            x_hat, _ = opt.model.box_optimum()
            line += f"  {(float(sim.loss_rate(x_hat)) - f0) / (f_star - f0):20.3f}"
            line += f"  {opt.last_info.get('inform')!s:>6}"
        if oracle and n > 0 and n % every == 0:
            model = copy.deepcopy(opt.model)  # the run itself is not touched
            X, Y = opt.train_data()
            model.fit(X, Y)
            truth = model.prior_theta().clone()
            truth[: model.dim] = mu_true  # log c and log beta of the oracle prior are the truth's
            res = minimize_lbfgsb(_NumpyObjective(model, X, Y), truth.numpy(), maxiter=1000)
            nlp_truth = float(model._neg_log_post(truth, X, Y))
            line += f"  {model.neg_log_post:8.2f}  {nlp_truth:10.2f}  {res.fun:21.2f}"
        print(line, flush=True)
        x = opt.ask()


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seeds", default="101-106", help="machine seeds (tune on 101 and up)")
    p.add_argument("--family", default="project", choices=sorted(FAMILIES))
    p.add_argument("--prior", default=PRIOR, help="prior JSON file")
    p.add_argument("--budget", type=int, default=50, help="evaluations per run")
    p.add_argument("--oracle", action="store_true", help="tell each machine's own peak")
    p.add_argument("--every", type=int, default=4, help="readings between fit comparisons")
    p.add_argument("--options", default="{}", help="pigp-physics options as JSON")
    p.add_argument("--directions", type=int, default=3, help="directions of the form check")
    args = p.parse_args(argv)
    prior = PhysicsPrior.load(args.prior)
    torch.set_num_threads(1)
    qs = (0.25, 1.0, 4.0, 9.0, 16.0, 25.0)
    for seed in seed_list(args.seeds):
        sim = benchmark_ring(seed, SPEAR3, True, family=args.family)
        mu, B = machine_peak(sim)
        ratio = quadratic_departure(sim.loss_rate, float(sim.loss_background), mu, B, qs,
                                    args.directions, seed)  # fmt: skip
        print(f"machine {seed}: (g - c)/q along {args.directions} random directions at q = "
              + ", ".join(f"{q:g}" for q in qs) + " (1 for the exact form):")  # fmt: skip
        for row in ratio:
            print("   " + " ".join(f"{r:6.3f}" for r in row))
        trace_run(prior, sim, seed, args.budget, args.oracle, args.every,
                  json.loads(args.options), args.family)  # fmt: skip


if __name__ == "__main__":
    main()
