r"""Named method specs of the benchmark: how to build each optimizer for one run.

A method is a :class:`MethodSpec`: a name, a builder ``(ctx: RunContext, **options) -> optimizer``,
the budget class (``"gp"`` or ``"direct"``, looked up in ``run_benchmark(budgets=...)``) and the
builder's keyword options. Specs are plain data, so a variant is one entry::

    METHODS["pigp-rq"] = MethodSpec("pigp-rq", build_pigp, "gp", {"kernel": "rq"})
    cheap = METHODS["pigp"].with_options(num_restarts=2, raw_samples=32)

Defaults (documented choices):

* BO methods (``pigp``, ``pigp-zero-mean``, ``ml2``): UCB with :math:`\beta = 4` (the authors'
  :math:`\mu + 2\sigma`), trust box of half-width ``step_limit = 0.3`` in knob units normalized
  to :math:`[-1, 1]` (the issue report: ±0.3 worked better than ±0.1), centered on the best
  noisy reading; acquisition optimized with ``num_restarts = 4`` L-BFGS-B restarts from
  ``raw_samples = 128`` Sobol points.
* ``ml2``: hyperparameters fitted on an archive of ``archive_size`` noisy machine readings at
  settings drawn from :math:`\mathcal N(0, (0.2 \cdot \text{half-range})^2)` per knob around
  skews-off (clipped to the bounds), then refitted online on archive ∪ run data every
  ``refit_every`` steps with a warm start from the previous hyperparameters; noise learned.
* ``pigp-physics-mean``: the PI-GP kernel and noise with the physics-structured mean
  :class:`~pigp_torch.models.PhysicsMean` (centre, peak and scale MAP-fitted at every ask,
  :func:`build_pigp_physics_mean`) and a wider trust box, ``step_limit = 0.6`` (on seeds 1–4 the
  fitted mean raised the median gain after 40 evaluations from 0.16 to 0.56 at ±0.3 and 0.65 at
  ±0.6; the plain PI-GP at ±0.6: 0.12). On held-out seeds 5–12 after 100 evaluations: median
  gain 0.68 vs 0.31 for ``pigp``; no run reaches 95 % of the optimum in 100 evaluations.
* ``pigp-physics``: :class:`~pigp_torch.optimizers.PhysicsModelBO`, the physics form fitted
  online, with the prior on its centre and its shape from the prior's error ensemble
  (``center_cov``, ``peak_shape``; the benchmark computes them from
  :data:`~pigp_torch.benchmark.protocol.ENSEMBLE_SIZE` model rings with seeds from 1001).
  ``pigp-physics-box``: the same with what the model ring alone gives, the method before the
  ensemble: its own shape and the isotropic box prior on the centre (1 half-range).
* ``nelder-mead``: adaptive coefficients, ``initial_simplex_size = 0.05`` of each knob's full
  range (= ±0.1 in the normalized units, 3 A on SPEAR3), restarts when converged.
* ``rcds``: ``noise = 0.04`` (the machine's), initial ``step = 0.05`` of the knob range,
  coordinate directions.
"""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import torch

from pigp_torch._utils import DTYPE
from pigp_torch.machine import SimulatedMachine
from pigp_torch.models import PhysicsMean, fit_physics_mean, ml2_gp, physics_informed_gp
from pigp_torch.optimizers import RCDS, BayesOpt, NelderMead
from pigp_torch.optimizers.base import AskTellOptimizer
from pigp_torch.optimizers.fast_bo import FastBayesOpt
from pigp_torch.optimizers.physics_bo import PhysicsModelBO
from pigp_torch.prior import PhysicsPrior

#: Budget classes of the protocol (evaluations, start point included).
DEFAULT_BUDGETS = {"gp": 100, "direct": 300}
#: Acquisition-optimization defaults of every BO method.
BO_DEFAULTS = {
    "acquisition": "ucb",
    "beta": 4.0,
    "step_limit": 0.3,
    "trust_center": "best_observed",
    "num_restarts": 4,
    "raw_samples": 128,
}


@dataclass(frozen=True)
class RunContext:
    r"""What a builder may use for one run.

    Attributes:
        machine: the noisy :class:`~pigp_torch.machine.SimulatedMachine` of this run.
        prior: the physics prior computed from the MODEL ring (never the machine).
        seed: the run's seed (derived from method name and machine seed).
        noise: the measurement noise standard deviation (mA/min).
        archive_size: number of archive samples for data-informed methods.
    """

    machine: SimulatedMachine
    prior: PhysicsPrior
    seed: int
    noise: float = 0.04
    archive_size: int = 300

    @property
    def bounds(self) -> torch.Tensor:
        return self.machine.bounds


@dataclass(frozen=True)
class MethodSpec:
    """One benchmark method: ``builder(ctx, **options)`` returns a fresh ask/tell optimizer.

    Attributes:
        name: value of the ``method`` column.
        builder: ``(RunContext, **options) -> AskTellOptimizer``.
        budget: budget class, a key of ``run_benchmark(budgets=...)`` (``"gp"``/``"direct"``).
        options: keyword options passed to ``builder``.
        uses_center_ensemble: the method reads the prior's ``center_cov`` (so
            :func:`~pigp_torch.benchmark.run_benchmark` computes the error ensemble for it).
    """

    name: str
    builder: Callable[..., AskTellOptimizer]
    budget: str
    options: Mapping[str, Any] = field(default_factory=dict)
    uses_center_ensemble: bool = False

    def build(self, ctx: RunContext) -> AskTellOptimizer:
        """A fresh optimizer for the run described by ``ctx``."""
        return self.builder(ctx, **dict(self.options))

    def with_options(self, name: str | None = None, **options) -> MethodSpec:
        """A copy with ``options`` overriding (and extending) this spec's options."""
        return dataclasses.replace(
            self, name=self.name if name is None else name, options={**self.options, **options}
        )


def _bayesopt(ctx: RunContext, factory, options: dict) -> BayesOpt:
    opts = {**BO_DEFAULTS, **options}
    return BayesOpt(ctx.bounds, factory, seed=ctx.seed, **opts)


def build_pigp(ctx: RunContext, *, kernel: str = "rbf", mean="f_inf", **bo_options) -> BayesOpt:
    r"""PI-GP Bayesian optimization: the kernel, mean and noise all come from ``ctx.prior``.

    Args:
        ctx: the run context.
        kernel: ``"rbf"`` (paper) or ``"rq"``.
        mean: ``"f_inf"`` (paper), ``"zero"`` (Fig. 2c) or a float.
        **bo_options: :class:`~pigp_torch.optimizers.BayesOpt` options over :data:`BO_DEFAULTS`.
    """
    prior = ctx.prior

    def factory(X, Y):
        return physics_informed_gp(X, Y, prior, kernel=kernel, mean=mean)

    return _bayesopt(ctx, factory, bo_options)


def fast_bo_options(options: Mapping[str, Any]) -> dict:
    """:class:`FastBayesOpt` options: ``options`` over the :data:`BO_DEFAULTS` it shares with
    :class:`BayesOpt` (acquisition, beta, step_limit, trust_center); its search keeps its own."""
    keys = ("acquisition", "beta", "step_limit", "trust_center")
    return {**{k: BO_DEFAULTS[k] for k in keys}, **options}


def build_pigp_fast(ctx: RunContext, *, mean="f_inf", **options) -> FastBayesOpt:
    r"""The ``"pigp"`` method on :class:`~pigp_torch.optimizers.fast_bo.FastBayesOpt`: the same
    fixed-kernel GP posterior (incremental Cholesky) and acquisition, :data:`BO_DEFAULTS` for
    ``acquisition``, ``beta``, ``step_limit`` and ``trust_center``, its own batched Newton
    acquisition search (12-18x faster per step at 13 knobs): :class:`FastBayesOpt`'s defaults, 10
    Newton restarts from the best of 256 random points plus the trust-box centre and the last two
    proposals."""
    return FastBayesOpt.from_prior(
        ctx.bounds, ctx.prior, mean=mean, seed=ctx.seed, **fast_bo_options(options)
    )


def build_pigp_physics_mean(
    ctx: RunContext,
    *,
    kernel: str = "rbf",
    center_prior: str = "zero",
    center_std: float = 0.5,
    log_std: float = 2.0,
    n_eigen_scales: int = 0,
    fit_iter: int = 50,
    **bo_options,
) -> BayesOpt:
    r"""PI-GP with the physics-structured mean :class:`~pigp_torch.models.PhysicsMean`.

    Kernel, noise and the mean's shape :math:`\Sigma` come from ``ctx.prior``; the mean's centre
    :math:`\mu`, peak :math:`A` and scale :math:`s` are MAP-fitted on all run data at every ask
    (:func:`~pigp_torch.models.fit_physics_mean`, warm-started from the previous fit) with priors
    :math:`\mu \sim \mathcal N(\mu_0, (\tau h)^2)` per knob (:math:`h` the half-range,
    :math:`\tau` = ``center_std``), :math:`\log A \sim \mathcal N(\log(f(x_0) - f_\infty),
    \lambda^2)`, :math:`\log s \sim \mathcal N(0, \lambda^2)` (:math:`\lambda` = ``log_std``).

    Args:
        ctx: the run context.
        kernel: ``"rbf"`` or ``"rq"``.
        center_prior: :math:`\mu_0`: ``"zero"`` (skews off) or ``"x0"`` (the model's optimum).
        center_std: :math:`\tau`, a fraction of each knob's half-range.
        log_std: :math:`\lambda`.
        n_eigen_scales: separate curvature scales along the top eigenvectors of :math:`\Sigma`
            (:class:`~pigp_torch.models.PhysicsMean`), with the same log-normal prior.
        fit_iter: L-BFGS iterations per fit.
        **bo_options: :class:`~pigp_torch.optimizers.BayesOpt` options over :data:`BO_DEFAULTS`.
    """
    if center_prior not in ("zero", "x0"):
        raise ValueError(f'center_prior must be "zero" or "x0", got {center_prior!r}')
    prior = ctx.prior
    lower, upper = ctx.bounds
    mu0 = prior.x0.clone() if center_prior == "x0" else (upper + lower) / 2
    tau = float(center_std) * (upper - lower) / 2
    mean = PhysicsMean.from_prior(prior, center=mu0, n_eigen_scales=n_eigen_scales)
    peak0 = prior.f_x0 - prior.f_inf

    def factory(X, Y):
        model = physics_informed_gp(X, Y, prior, kernel=kernel, mean=mean)
        with torch.no_grad():
            cov = model.covar_module(X).to_dense()
        cov = cov + prior.noise**2 * torch.eye(X.shape[0], dtype=DTYPE)
        fit_physics_mean(
            mean,
            X,
            Y,
            cov,
            center_prior=mu0,
            center_std=tau,
            peak_prior=peak0,
            log_std=log_std,
            max_iter=fit_iter,
        )
        return physics_informed_gp(X, Y, prior, kernel=kernel, mean=copy.deepcopy(mean))

    return _bayesopt(ctx, factory, bo_options)


def build_pigp_physics(ctx: RunContext, **options) -> PhysicsModelBO:
    r"""UCB on the online-fitted physics form :math:`f_\infty + (c + \beta(\mathbf x -
    \boldsymbol\mu)^\top B(\mathbf x - \boldsymbol\mu))^{-1/2}`, :math:`B` from ``ctx.prior``
    (:class:`~pigp_torch.optimizers.physics_bo.PhysicsModelBO`; options override its defaults:
    ``beta=4``, ``step_limit=0.6``, ``residual_std=0.05``, the centre prior and the shape from
    the prior's error ensemble when it has one, else ``center_std=1.0`` half-range around the
    box centre and the model ring's shape)."""
    return PhysicsModelBO(ctx.bounds, ctx.prior, seed=ctx.seed, noise=ctx.noise, **options)


def machine_archive(
    machine: SimulatedMachine, size: int, *, spread: float = 0.2, seed: int = 0
) -> tuple[torch.Tensor, torch.Tensor]:
    r"""``size`` noisy readings of ``machine`` near skews-off (an operating-point archive).

    Settings :math:`x_i \sim \mathcal N(0, (s\,h)^2)` per knob (:math:`h` the half-range,
    :math:`s` = ``spread``) clipped to the bounds; readings :math:`f(x_i) + \epsilon_i`,
    :math:`\epsilon_i \sim \mathcal N(0, \sigma_n^2)` with the machine's noise level, drawn from a
    generator seeded by ``seed`` (the machine's own noise stream is not touched).

    Returns:
        ``(X_a: size x d, Y_a: size)``.
    """
    if int(size) < 1:
        raise ValueError(f"archive size must be >= 1, got {size}")
    gen = torch.Generator().manual_seed(int(seed))
    lower, upper = machine.bounds
    center, half = (upper + lower) / 2, (upper - lower) / 2
    Z = torch.randn(int(size), machine.dim, generator=gen, dtype=DTYPE)
    X = torch.minimum(torch.maximum(center + spread * half * Z, lower), upper)
    eps = torch.randn(int(size), generator=gen, dtype=DTYPE)
    return X, machine.true_value(X) + machine.noise * eps


def build_ml2(
    ctx: RunContext,
    *,
    archive_spread: float = 0.2,
    refit_every: int = 1,
    learn_noise: bool = True,
    **bo_options,
) -> BayesOpt:
    r"""ML-II Bayesian optimization: diagonal ARD RBF fitted on an archive of machine data.

    Hyperparameters are fitted once on the archive (:func:`machine_archive`), then refitted on
    archive ∪ run data every ``refit_every`` asks, warm-started from the previous fit; between
    refits they are frozen. The GP itself is conditioned on the run data only.

    Args:
        ctx: the run context (``ctx.archive_size`` readings).
        archive_spread: archive standard deviation as a fraction of the half-range.
        refit_every: refit period in asks (``0``: never refit, archive fit only).
        learn_noise: learn the noise by ML-II (default) or fix it to ``ctx.noise``.
        **bo_options: :class:`~pigp_torch.optimizers.BayesOpt` options over :data:`BO_DEFAULTS`.
    """
    if int(refit_every) < 0:
        raise ValueError(f"refit_every must be >= 0, got {refit_every}")
    archive = machine_archive(ctx.machine, ctx.archive_size, spread=archive_spread, seed=ctx.seed)
    bounds = ctx.bounds
    noise = None if learn_noise else ctx.noise
    state = {"hyper": None, "calls": 0}

    def factory(X, Y):
        refit = state["hyper"] is None or (
            refit_every > 0 and state["calls"] % int(refit_every) == 0
        )
        model = ml2_gp(
            X,
            Y,
            bounds=bounds,
            archive=archive,
            refit=refit,
            noise=noise,
            state_dict=state["hyper"],
        )
        state["calls"] += 1
        if refit:
            state["hyper"] = {k: v.detach().clone() for k, v in model.state_dict().items()}
        return model

    return _bayesopt(ctx, factory, bo_options)


def build_nelder_mead(
    ctx: RunContext, *, initial_simplex_size: float = 0.05, **options
) -> NelderMead:
    """Nelder–Mead (adaptive coefficients) with the documented initial simplex."""
    return NelderMead(ctx.bounds, initial_simplex_size=initial_simplex_size, **options)


def build_rcds(ctx: RunContext, *, step: float = 0.05, noise: float | None = None) -> RCDS:
    """RCDS with the machine's noise level (``noise=None``: ``ctx.noise``)."""
    return RCDS(ctx.bounds, noise=ctx.noise if noise is None else noise, step=step)


#: The registry of named methods (add variants here: one entry each).
METHODS: dict[str, MethodSpec] = {
    "pigp": MethodSpec("pigp", build_pigp, "gp"),
    "pigp-zero-mean": MethodSpec("pigp-zero-mean", build_pigp, "gp", {"mean": "zero"}),
    "pigp-physics-mean": MethodSpec(
        "pigp-physics-mean", build_pigp_physics_mean, "gp", {"step_limit": 0.6}
    ),
    "pigp-fast": MethodSpec("pigp-fast", build_pigp_fast, "gp"),
    "pigp-physics": MethodSpec("pigp-physics", build_pigp_physics, "gp", {}, True),
    "pigp-physics-box": MethodSpec(
        "pigp-physics-box",
        build_pigp_physics,
        "gp",
        {"center_prior": "box", "shape_prior": "model"},
    ),
    "ml2": MethodSpec("ml2", build_ml2, "gp"),
    "nelder-mead": MethodSpec("nelder-mead", build_nelder_mead, "direct"),
    "rcds": MethodSpec("rcds", build_rcds, "direct"),
}


def resolve_methods(methods) -> list[MethodSpec]:
    """Names (looked up in :data:`METHODS`) or :class:`MethodSpec` objects -> specs.

    Raises:
        ValueError: unknown name, duplicate method names, or an empty list.
    """
    if isinstance(methods, (str, MethodSpec)):
        methods = [methods]
    specs = []
    for m in methods:
        if isinstance(m, MethodSpec):
            specs.append(m)
        elif m in METHODS:
            specs.append(METHODS[m])
        else:
            raise ValueError(f"unknown method {m!r}; known: {sorted(METHODS)}")
    names = [s.name for s in specs]
    if not specs:
        raise ValueError("no methods given")
    if len(set(names)) != len(names):
        raise ValueError(f"duplicate method names in {names}")
    return specs


# Xopt-backed methods (pigp_torch.benchmark.xopt_methods): the builders import Xopt only when a
# run is built, so the benchmark does not need Xopt unless these methods are used.
from pigp_torch.benchmark.xopt_methods import XOPT_METHODS  # noqa: E402

METHODS.update(XOPT_METHODS)
