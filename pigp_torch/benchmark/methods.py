r"""The benchmark's methods: every registered method and the benchmark's own variants.

:data:`METHODS` is :data:`pigp_torch.methods.METHODS` (the product methods, see
:mod:`pigp_torch.methods`) plus the variants that only the benchmark compares:

* ``pigp-zero-mean``: ``pigp`` with a zero prior mean (Fig. 2c);
* ``pigp-physics-mean``: the PI-GP kernel and noise with the physics-structured mean
  :class:`~pigp_torch.models.PhysicsMean` (centre, peak and scale MAP-fitted at every ask,
  :func:`build_pigp_physics_mean`) and a wider trust box, ``step_limit = 0.6``;
* ``pigp-physics-box``: ``pigp-physics`` with what the model ring alone gives: its own shape and
  the isotropic box prior on the centre (1 half-range), no error ensemble.

A further variant is one entry: ``METHODS["pigp-rq"] = METHODS["pigp"].with_options(
name="pigp-rq", kernel="rq")``. ``ml2`` is fitted on an archive of ``archive_size`` noisy
machine readings (:func:`~pigp_torch.methods.gp.machine_archive`) in the benchmark.
"""

from __future__ import annotations

import copy

import torch

from pigp_torch._utils import DTYPE
from pigp_torch.methods import (
    BO_DEFAULTS,
    DEFAULT_BUDGETS,
    MethodSpec,
    RunContext,
    build_ml2,
    build_nelder_mead,
    build_pigp,
    build_pigp_fast,
    build_pigp_physics,
    build_rcds,
    fast_bo_options,
    machine_archive,
)
from pigp_torch.methods import METHODS as _PRODUCT_METHODS
from pigp_torch.methods import resolve_methods as _resolve_methods
from pigp_torch.methods.gp import bayesopt
from pigp_torch.models import PhysicsMean, fit_physics_mean, physics_informed_gp
from pigp_torch.optimizers import BayesOpt


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

    return bayesopt(ctx, factory, bo_options)


#: The benchmark's methods: the registered ones and the variants above (add variants here).
METHODS: dict[str, MethodSpec] = {
    **_PRODUCT_METHODS,
    "pigp-zero-mean": MethodSpec("pigp-zero-mean", build_pigp, "gp", {"mean": "zero"}),
    "pigp-physics-mean": MethodSpec(
        "pigp-physics-mean", build_pigp_physics_mean, "gp", {"step_limit": 0.6}
    ),
    "pigp-physics-box": MethodSpec(
        "pigp-physics-box",
        build_pigp_physics,
        "gp",
        {"center_prior": "box", "shape_prior": "model"},
    ),
}


def resolve_methods(methods) -> list[MethodSpec]:
    """Names (looked up in :data:`METHODS`) or :class:`MethodSpec` objects -> specs.

    Raises:
        ValueError: unknown name, duplicate method names, or an empty list.
    """
    return _resolve_methods(methods, METHODS)


__all__ = [
    "BO_DEFAULTS",
    "DEFAULT_BUDGETS",
    "METHODS",
    "MethodSpec",
    "RunContext",
    "build_ml2",
    "build_nelder_mead",
    "build_pigp",
    "build_pigp_fast",
    "build_pigp_physics",
    "build_pigp_physics_mean",
    "build_rcds",
    "fast_bo_options",
    "machine_archive",
    "resolve_methods",
]
