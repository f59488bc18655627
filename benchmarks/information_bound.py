r"""How many readings does the noise allow? An oracle design for each machine.

The benchmark scores a run by the best noise-free loss rate it visited and asks for 95 % of the
achievable gain, :math:`f \ge f^* - \Delta` with :math:`\Delta = 0.05\,(f^* - f_0)`. To put a
setting there on purpose, an optimizer must know where the box optimum is to that precision, and
with readings of noise :math:`\sigma_n` that takes a number of readings no design can beat. This
script estimates that number for each machine with everything in the optimizer's favour:

* the machine's own physics form is known exactly (its unconstrained optimum
  :math:`\boldsymbol\mu`, its shape :math:`B` there and :math:`c = (f(\boldsymbol\mu) -
  f_\infty)^{-2}`, from :func:`~pigp_torch.bench.oracle.machine_peak`), so the only
  error is the noise;
* the parameters :math:`\theta = (\boldsymbol\mu, \log c, \log\beta)` carry the same priors as in
  ``pigp-physics`` (the ensemble's centre covariance), and the Laplace covariance
  :math:`C = (J^\top J/\sigma_n^2 + \Lambda_0)^{-1}` of a design is that of
  :class:`~pigp_torch.models.InverseSqrtPeakModel` at the TRUE :math:`\theta`;
* the readings are chosen greedily, each one where it most lowers the expected regret of the
  recommendation (A-optimal design, Sherman-Morrison updates), from Sobol points of the knob box
  and clouds around the optimum; the climb from the start point is free.

The recommendation is the form's box optimum :math:`\hat{\mathbf x}`
(:meth:`~pigp_torch.models.InverseSqrtPeakModel.box_optimum`); an error of the centre costs
:math:`\tfrac12\,\beta\, g(\hat{\mathbf x})^{-3/2}\,\boldsymbol\delta^\top M\boldsymbol\delta` with
:math:`M` from :meth:`~pigp_torch.models.InverseSqrtPeakModel.regret_metric` (the loss is flat
across the box face), so the expected regret after the design is

.. math:: R = \tfrac12\,\beta\,g(\hat{\mathbf x})^{-3/2}\,\mathrm{tr}(M\,C_{\mu\mu}).

``n95`` is the number of designed readings after which :math:`R \le \Delta`. It is a rough
bound, not a proof: the form is the machine's local fit, :math:`R` is a mean (a run can land
closer by luck), and a real run must also climb from the start point and learn
:math:`\boldsymbol\mu` first. A machine whose ``n95`` is near or above 40 cannot be expected to
reach 95 % within 40 evaluations by any method that must find its optimum from readings.

The machines are the benchmark's (each with its own loss-rate map unless ``--model-maps``), of
the family ``--family`` (``project``, default, or ``wide``:
:mod:`~pigp_torch.bench.families`); the oracle also knows the machine's own background.
Results: ``docs/results.md``.

Usage::

    python benchmarks/information_bound.py --prior runs/prior_surrogate.json \
        --seeds $(seq 1 24) --csv runs/n95.csv
"""

from __future__ import annotations

import argparse
import dataclasses
import math

import torch

from pigp_torch._utils import DTYPE
from pigp_torch.bench import model_prior
from pigp_torch.bench.families import FAMILIES
from pigp_torch.bench.oracle import machine_peak
from pigp_torch.bench.protocol import benchmark_ring, machine_optimum
from pigp_torch.models import InverseSqrtPeakModel
from pigp_torch.prior import PhysicsPrior
from pigp_torch.simulation.ring import RingCoupling
from pigp_torch.simulation.spec import SPEAR3


def candidates(model: InverseSqrtPeakModel, x_hat: torch.Tensor, n_sobol: int, seed: int):
    """Sobol points of the knob box plus Gaussian clouds around ``x_hat`` at radii 0.25-2 of the
    peak width :math:`\\sqrt{c/\\beta}` in the metric of B, clipped to the box."""
    lo, hi = model.bounds
    d = model.dim
    sobol = torch.quasirandom.SobolEngine(d, scramble=True, seed=seed).draw(n_sobol).to(DTYPE)
    gen = torch.Generator().manual_seed(seed)
    theta = model.theta
    width = math.exp(0.5 * float(theta[d] - theta[d + 1]))
    L = torch.linalg.cholesky(model.shape())
    clouds = []
    for radius in (0.25, 0.5, 0.7, 1.0, 1.4, 2.0):
        z = torch.randn(n_sobol // 4, d, generator=gen, dtype=DTYPE)
        z = z / z.norm(dim=1, keepdim=True) * radius * width
        clouds.append(x_hat + torch.linalg.solve_triangular(L.T, z.T, upper=True).T)
    X = torch.cat([lo + (hi - lo) * sobol, *clouds])
    return torch.minimum(torch.maximum(X, lo), hi)


def greedy_design(model: InverseSqrtPeakModel, X: torch.Tensor, budget: int, bar: float):
    """Greedy A-optimal readings from the candidates ``X``; returns the regret after each and
    the chosen rows of ``X``."""
    d = model.dim
    x_hat, _ = model.box_optimum()
    M = model.regret_metric()
    theta = model.theta
    g_hat = float(model.g(x_hat, theta))
    scale = 0.5 * math.exp(float(theta[d + 1])) * g_hat**-1.5
    model._laplace(X[:0])  # the prior alone: C = Lambda_0^-1
    C = model.cov.clone()
    J = model.jacobian(X)
    s2 = model.noise**2
    regrets = [scale * float(torch.trace(M @ C[:d, :d]))]
    chosen = []
    for _ in range(budget):
        V = J @ C
        Vmu = V[:, :d]
        drop = ((Vmu @ M) * Vmu).sum(1) / (s2 + (V * J).sum(1))
        k = int(drop.argmax())
        chosen.append(k)
        v = V[k]
        C = C - torch.outer(v, v) / (s2 + float(v @ J[k]))
        regrets.append(scale * float(torch.trace(M @ C[:d, :d])))
        if regrets[-1] <= bar:
            break
    return regrets, X[chosen]


def replay(
    model: InverseSqrtPeakModel,
    sim: RingCoupling,
    X: torch.Tensor,
    f_star: float,
    repeats: int,
    seed: int,
) -> torch.Tensor:
    r"""Read the design ``X`` on the simulated machine ``repeats`` times (fresh noise), refit the
    form each time (warm start at the truth) and return the TRUE regret :math:`f^* -
    f(\hat{\mathbf x})` of each fit's box optimum: checks the Laplace estimate and the form."""
    gen = torch.Generator().manual_seed(seed)
    f = sim.loss_rate(X)
    truth = model.theta.clone()
    out = []
    for _ in range(repeats):
        Y = f + model.noise * torch.randn(f.shape, generator=gen, dtype=DTYPE)
        model.theta = truth.clone()
        model.fit(X, Y)
        out.append(f_star - float(sim.loss_rate(model.box_optimum()[0])))
    model.theta = truth
    return torch.tensor(out, dtype=DTYPE)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", required=True, help="machine error seeds")
    ap.add_argument("--prior", default=None, help="prior JSON (default: model ring 0 + ensemble)")
    ap.add_argument(
        "--center-ensemble", type=int, default=40,
        help="ensemble rings of the default prior (default 40; ignored with --prior)",
    )  # fmt: skip
    ap.add_argument(
        "--max-readings", type=int, default=400,
        help="stop a design here if the regret is still above the bar (default 400)",
    )  # fmt: skip
    ap.add_argument("--candidates", type=int, default=4096, help="Sobol candidates (default 4096)")
    ap.add_argument(
        "--replays", type=int, default=0,
        help="read the n95 design this many times on the simulated machine, refit, and report "
        "the true regret of the fitted optimum (mean and share under the bar)",
    )  # fmt: skip
    ap.add_argument(
        "--model-maps", action="store_true",
        help="machines with the model's loss-rate constants (default: each its own map, as in "
        "the benchmark)",
    )  # fmt: skip
    ap.add_argument(
        "--family", choices=FAMILIES, default="project",
        help="machine family (default project; wide: re-tuned deck, drawn error scale, peak and "
        "background per machine, own loss-rate maps only)",
    )  # fmt: skip
    ap.add_argument("--csv", default=None, help="also write seed, n95, bar, ... to this CSV")
    args = ap.parse_args(argv)
    if args.family == "wide" and args.model_maps:
        ap.error("the wide family draws each machine's own loss-rate map: drop --model-maps")
    torch.set_default_dtype(DTYPE)
    if args.prior:
        prior = PhysicsPrior.load(args.prior)
    else:
        print(f"model prior: ring 0 + {args.center_ensemble} ensemble rings ...", flush=True)
        prior = model_prior(0, center_ensemble=args.center_ensemble)
    print(f"noise {prior.noise}; regret bar = 5 % of the machine's gain f* - f0")
    print(
        f"{'seed':>4} {'f0':>6} {'f*':>6} {'bar':>6} {'beyond':>7} {'free':>4} "
        f"{'R_prior':>8} {'R@20':>7} {'R@40':>7} {'n95':>5}"
        + ("  replay: mean regret/bar, share <= bar" if args.replays else "")
    )
    maps = not args.model_maps
    rows = []
    for seed in args.seeds:
        sim = benchmark_ring(seed, SPEAR3, maps, args.family)
        if list(sim.knob_names) != list(prior.knob_names):
            raise SystemExit("the prior is for other knobs than the benchmark's (paper13)")
        mu, B = machine_peak(sim)
        f_mu = float(sim.loss_rate(mu))
        # the oracle knows the machine's own background too
        own = dataclasses.replace(prior, f_inf=float(sim.loss_background))
        model = InverseSqrtPeakModel(
            own, sim.bounds, shape=B, center_cov=prior.center_cov, residual_std=0.0
        )
        model.theta = torch.cat(
            [mu, torch.tensor([-2.0 * math.log(f_mu - model.f_inf), 0.0], dtype=DTYPE)]
        )
        f0 = float(sim.loss_rate(torch.zeros(sim.dim, dtype=DTYPE)))
        f_star = machine_optimum(seed, 8, machine_maps=maps, family=args.family)
        bar = 0.05 * (f_star - f0)
        x_hat, active = model.box_optimum()
        half = (sim.bounds[1] - sim.bounds[0]) / 2
        beyond = float((mu.abs() / half).max())  # > 1: the optimum lies outside the box
        regrets, design = greedy_design(
            model, candidates(model, x_hat, args.candidates, seed), args.max_readings, bar
        )
        n95 = len(regrets) - 1 if regrets[-1] <= bar else f">{args.max_readings}"

        def at(n, r=regrets):
            return f"{r[n]:.4f}" if n < len(r) else "<bar"

        check = ""
        if args.replays:
            regret = replay(model, sim, design, f_star, args.replays, seed)
            share = float((regret <= bar).double().mean())
            check = f"  {float(regret.mean()) / bar:.2f}, {share:.2f}"
        print(
            f"{seed:>4} {f0:>6.3f} {f_star:>6.3f} {bar:>6.4f} {beyond:>7.2f} "
            f"{int((~active).sum()):>4} {regrets[0]:>8.4f} {at(20):>7} {at(40):>7} {n95:>5}"
            + check,
            flush=True,
        )
        rows.append({"family": args.family, "machine_seed": seed,
                     "n95": n95 if isinstance(n95, int) else float("inf"),
                     "bar": bar, "f0": f0, "f_star": f_star, "beyond": beyond})  # fmt: skip
    if args.csv:
        import pandas as pd

        pd.DataFrame(rows).to_csv(args.csv, index=False)


if __name__ == "__main__":
    main()
