r"""Step time of physics-informed BO: :class:`FastBayesOpt` vs the stock BoTorch path.

A *step* is what the loop spends in the optimizer per evaluation: ``tell`` the last measurement
(model update) plus ``ask`` (acquisition optimization). Three paths are timed on the same data:

* ``fast``: :class:`~pigp_torch.optimizers.FastBayesOpt` (incremental exact posterior, closed-form
  derivatives, batched projected Newton / stacked L-BFGS-B);
* ``stock``: :class:`~pigp_torch.optimizers.BayesOpt` with
  :func:`~pigp_torch.models.physics_informed_gp` -- a ``SingleTaskGP`` built from scratch and
  ``optimize_acqf`` with ``UpperConfidenceBound``, ``num_restarts = 10``, ``raw_samples = 256``;
* ``ml2``: the ML-II GP (:func:`~pigp_torch.models.ml2_gp`, diagonal ARD RBF, hyperparameters
  refitted at every step by ``fit_gpytorch_mll`` warm-started from the previous step's values)
  with the same stock ``optimize_acqf`` settings.

The test problem is synthetic (no simulator needed, any ``d``): knobs in :math:`[-h, h]^d` with
:math:`h = 0.015`, a random full precision matrix :math:`P` with condition number 483 (the
authors' SPEAR3 value), objective :math:`f(\mathbf x) = f_\infty + (f_0 - f_\infty)
\exp(-\tfrac12 (\mathbf x - \mathbf x_0)^\top P (\mathbf x - \mathbf x_0)) + \varepsilon`,
:math:`\varepsilon \sim \mathcal N(0, 0.04^2)`, and the PI-GP prior built from the same
:math:`P`. For each ``(d, n)`` the optimizers are told ``n`` points (a seeded design in the box),
then ``repeats`` steps are timed, each telling the previous proposal's reading and asking.
"""

from __future__ import annotations

import functools
import platform
import sys
import time

import numpy as np
import torch

from pigp_torch._utils import DTYPE
from pigp_torch.methods import BO_DEFAULTS, RunContext, build_pigp_fast  # noqa: F401
from pigp_torch.models import ml2_gp, physics_informed_gp
from pigp_torch.optimizers import BayesOpt
from pigp_torch.optimizers.fast_bo import FastBayesOpt
from pigp_torch.prior import PhysicsPrior

#: Sizes of the benchmark: observations and knob counts.
DEFAULT_NS = (10, 50, 150, 500)
DEFAULT_DIMS = (13, 72)
#: The stock path's ``optimize_acqf`` settings (the benchmark's definition).
STOCK_OPTIONS = {"num_restarts": 10, "raw_samples": 256}
#: FastBayesOpt's search as in the benchmark method ``pigp-fast`` (10 Newton restarts).
FAST_OPTIONS = {"num_restarts": 10, "raw_samples": 256}
#: Options shared by every path of the speed benchmark.
STEP_OPTIONS = {"acquisition": "ucb", "beta": 4.0, "step_limit": 0.3}
HALF_RANGE = 0.015
CONDITION = 483.0
NOISE = 0.04


def synthetic_problem(d: int, seed: int = 0):
    r"""The benchmark's test problem in ``d`` knobs: ``(prior, objective, bounds)``.

    ``objective(X: N x d) -> N`` is noise-free; the prior has precision :math:`P` (eigenvalues
    log-spaced over ``CONDITION``, random rotation), :math:`f_\infty = 0.2`, peak 1.7 at a random
    :math:`\mathbf x_0` inside the box, :math:`\sigma_f^2 = 1.5^2/12`, :math:`\sigma_n = 0.04`.
    """
    if int(d) < 1:
        raise ValueError(f"d must be >= 1, got {d}")
    g = np.random.default_rng(seed)
    Q, _ = np.linalg.qr(g.standard_normal((d, d)))
    # correlation lengths from 0.25 to 0.25 * sqrt(483) of the half-range
    eig = np.geomspace(1.0, CONDITION, d) / (0.25 * HALF_RANGE) ** 2 / CONDITION
    P = Q @ np.diag(eig) @ Q.T
    P = torch.tensor(0.5 * (P + P.T), dtype=DTYPE)
    bounds = torch.tensor([[-HALF_RANGE] * d, [HALF_RANGE] * d], dtype=DTYPE)
    x0 = torch.tensor(g.uniform(-0.5, 0.5, d) * HALF_RANGE, dtype=DTYPE)
    prior = PhysicsPrior(
        x0=x0,
        f_x0=1.7,
        f_inf=0.2,
        precision=P,
        amplitude=1.5**2 / 12,
        noise=NOISE,
        knob_names=[f"k{i}" for i in range(d)],
        bounds=bounds,
    )

    def objective(X: torch.Tensor) -> torch.Tensor:
        dx = X - x0
        return 0.2 + 1.5 * torch.exp(-0.5 * ((dx @ P) * dx).sum(-1))

    return prior, objective, bounds


def _quantiles(times: tuple[list[float], list[float]]) -> dict:
    """Median and 90th percentile of wall-clock and CPU step times (ms)."""
    wall, cpu = (np.asarray(t) * 1e3 for t in times)
    return {
        "median_ms": float(np.median(wall)),
        "p90_ms": float(np.quantile(wall, 0.9)),
        "cpu_median_ms": float(np.median(cpu)),
        "cpu_p90_ms": float(np.quantile(cpu, 0.9)),
        "n_steps": len(wall),
    }


def _time_steps(opt, X, Y, objective, repeats: int, gen):
    """Tell ``X[:-1], Y[:-1]``; then ``repeats`` timed steps (tell the previous reading, ask).

    Returns ``((wall_times, cpu_times), first)``: wall-clock and process CPU seconds per step and
    the FIRST proposal (made on exactly ``X, Y``)."""
    for x, y in zip(X[:-1], Y[:-1], strict=True):
        opt.tell(x, float(y))
    x_next, y_next = X[-1], float(Y[-1])
    wall, cpu, first = [], [], None
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        opt.tell(x_next, y_next)
        x_next = opt.ask()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
        first = x_next.clone() if first is None else first
        y_next = float(objective(x_next[None])[0]) + NOISE * float(
            torch.randn((), generator=gen, dtype=DTYPE)
        )
    return (wall, cpu), first


def _ml2_factory(bounds):
    """ML-II factory refitting at every call, warm-started from the previous hyperparameters."""
    state = {"hyper": None}

    def factory(X, Y):
        model = ml2_gp(X, Y, bounds=bounds, refit=True, state_dict=state["hyper"])
        state["hyper"] = {k: v.detach().clone() for k, v in model.state_dict().items()}
        return model

    return factory


def bo_step_times(
    ns=DEFAULT_NS,
    dims=DEFAULT_DIMS,
    *,
    repeats: int = 10,
    stock_repeats: int | None = None,
    ml2: bool = True,
    ml2_max_n: int = 150,
    seed: int = 0,
    progress: bool = False,
) -> dict:
    r"""Median and 90th-percentile step times of the fast, stock and ML-II paths.

    Args:
        ns: observation counts :math:`n` before the timed steps.
        dims: knob counts :math:`d`.
        repeats: timed steps of the fast path per ``(d, n)``.
        stock_repeats: timed steps of the stock and ML-II paths (default ``repeats``; they are
            slower per step than the fast path: fewer repeats keep the benchmark short).
        ml2: also time the warm-started ML-II path.
        ml2_max_n: skip ML-II above this ``n`` (its fit is :math:`O(n^3)` per iteration).
        seed: seed of the problem, the design and the noise.
        progress: print one line per measurement to stderr.

    Returns:
        ``{"config": {...}, "results": [row, ...]}``; one row per ``(d, n)`` with ``d``, ``n``,
        ``fast``, ``stock``, ``ml2`` (each ``{"median_ms", "p90_ms", "cpu_median_ms",
        "cpu_p90_ms", "n_steps"}``: wall-clock and process-CPU step times, the CPU time being the
        robust one on a shared host; ``ml2`` is ``None`` when skipped), ``fast_solver``,
        ``speedup_median``, ``speedup_p90`` and ``speedup_cpu_median`` (stock / fast) and
        ``acq_gap`` (the UCB of the BoTorch model on the same ``n`` points at the stock path's
        first proposal minus at the fast path's; <= 0: fast found at least as good a point).
    """
    ns = [int(n) for n in ns]
    dims = [int(d) for d in dims]
    if not ns or min(ns) < 1 or not dims or min(dims) < 1:
        raise ValueError(f"ns and dims must be non-empty lists of positive integers: {ns}, {dims}")
    repeats = int(repeats)
    stock_repeats = repeats if stock_repeats is None else int(stock_repeats)
    if repeats < 1 or stock_repeats < 1:
        raise ValueError(f"repeats must be >= 1, got {repeats}, {stock_repeats}")
    rows = []
    for d in dims:
        prior, objective, bounds = synthetic_problem(d, seed)
        for n in ns:
            gen = torch.Generator().manual_seed(seed + 1000 * d + n)
            X = bounds[0] + (bounds[1] - bounds[0]) * torch.rand(n, d, generator=gen, dtype=DTYPE)
            Y = objective(X) + NOISE * torch.randn(n, generator=gen, dtype=DTYPE)
            row: dict = {"d": d, "n": n}

            fast = FastBayesOpt.from_prior(bounds, prior, seed=seed, **STEP_OPTIONS, **FAST_OPTIONS)
            gen_f = torch.Generator().manual_seed(seed)
            times, x_fast = _time_steps(fast, X, Y, objective, repeats, gen_f)
            row["fast"] = _quantiles(times)
            row["fast_solver"] = fast.last_info["solver"]
            _report(progress, d, n, "fast", row["fast"])

            stock = BayesOpt(
                bounds,
                functools.partial(physics_informed_gp, prior=prior),
                seed=seed,
                **STEP_OPTIONS,
                **STOCK_OPTIONS,
            )
            gen_s = torch.Generator().manual_seed(seed)
            times, x_stock = _time_steps(stock, X, Y, objective, stock_repeats, gen_s)
            row["stock"] = _quantiles(times)
            _report(progress, d, n, "stock", row["stock"])
            row["speedup_median"] = row["stock"]["median_ms"] / row["fast"]["median_ms"]
            row["speedup_p90"] = row["stock"]["p90_ms"] / row["fast"]["p90_ms"]
            row["speedup_cpu_median"] = row["stock"]["cpu_median_ms"] / row["fast"]["cpu_median_ms"]
            row["acq_gap"] = _acq_gap(X, Y, prior, x_stock, x_fast)

            row["ml2"] = None
            if ml2 and n <= ml2_max_n:
                opt = BayesOpt(
                    bounds, _ml2_factory(bounds), seed=seed, **STEP_OPTIONS, **STOCK_OPTIONS
                )
                gen_m = torch.Generator().manual_seed(seed)
                row["ml2"] = _quantiles(_time_steps(opt, X, Y, objective, stock_repeats, gen_m)[0])
                _report(progress, d, n, "ml2", row["ml2"])
            rows.append(row)
    return {
        "config": {
            "ns": ns,
            "dims": dims,
            "repeats": repeats,
            "stock_repeats": stock_repeats,
            "stock": {**STEP_OPTIONS, **STOCK_OPTIONS, "model": "physics_informed_gp"},
            "fast": {**STEP_OPTIONS, **FAST_OPTIONS, "class": "FastBayesOpt"},
            "ml2": "ml2_gp refit every step, warm-started, stock optimize_acqf",
            "torch_threads": torch.get_num_threads(),
            "python": sys.version.split()[0],
            "machine": platform.machine(),
        },
        "results": rows,
    }


def _acq_gap(X, Y, prior: PhysicsPrior, x_stock, x_fast) -> float:
    """UCB of the BoTorch PI-GP on ``(X, Y)`` at the stock proposal minus at the fast one."""
    from botorch.acquisition import UpperConfidenceBound

    acq = UpperConfidenceBound(physics_informed_gp(X, Y, prior), beta=STEP_OPTIONS["beta"])
    with torch.no_grad():
        return float(acq(x_stock[None, None]) - acq(x_fast[None, None]))


def _report(progress: bool, d: int, n: int, path: str, q: dict) -> None:
    if progress:
        print(
            f"d={d:3d} n={n:4d} {path:5s} median {q['median_ms']:9.1f} ms  "
            f"p90 {q['p90_ms']:9.1f} ms  cpu median {q['cpu_median_ms']:9.1f} ms "
            f"({q['n_steps']} steps)",
            file=sys.stderr,
            flush=True,
        )


def format_table(result: dict) -> str:
    """A readable table of :func:`bo_step_times`' result."""

    def path(q: dict | None) -> str:
        if q is None:
            return f"{'-':>8} {'-':>8} {'-':>8}"
        return f"{q['median_ms']:8.1f} {q['p90_ms']:8.1f} {q['cpu_median_ms']:8.1f}"

    head = f"{'median':>8} {'p90':>8} {'cpu med':>8}"
    lines = [
        f"{'':8} | {'fast':^26} | {'stock':^26} | {'stock / fast':^20} | {'ml2':^26} |",
        f"{'d':>3} {'n':>4} | {head} | {head} | {'median':>6} {'p90':>6} {'cpu':>6} | {head} | "
        f"{'acq gap':>8} | solver",
    ]
    for r in result["results"]:
        lines.append(
            f"{r['d']:>3} {r['n']:>4} | {path(r['fast'])} | {path(r['stock'])} | "
            f"{r['speedup_median']:6.1f} {r['speedup_p90']:6.1f} {r['speedup_cpu_median']:6.1f} | "
            f"{path(r['ml2'])} | {r['acq_gap']:8.1e} | {r['fast_solver']}"
        )
    lines.append(
        "ms per step (tell + ask), wall-clock median / p90 and process-CPU median; acq gap = "
        "UCB(stock proposal) - UCB(fast proposal) on the same data (<= 0: fast at least as good)"
    )
    return "\n".join(lines)


__all__ = ["bo_step_times", "build_pigp_fast", "format_table", "synthetic_problem"]
