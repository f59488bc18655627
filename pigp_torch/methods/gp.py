r"""GP Bayesian optimization methods on :class:`~pigp_torch.optimizers.BayesOpt`: PI-GP and ML-II.

Defaults: :data:`~pigp_torch.optimizers.bo.defaults.BO_DEFAULTS` (those of the classes too).
"""

from __future__ import annotations

from typing import Any

import torch

from pigp_torch._utils import DTYPE
from pigp_torch.methods.registry import RunContext
from pigp_torch.models import ml2_gp, physics_informed_gp
from pigp_torch.optimizers import BayesOpt
from pigp_torch.optimizers.bo.defaults import BO_DEFAULTS


def bayesopt(ctx: RunContext, factory, options: dict) -> BayesOpt:
    """:class:`BayesOpt` on ``factory`` with ``options`` over :data:`BO_DEFAULTS`."""
    opts = {**BO_DEFAULTS, **options}
    return BayesOpt(ctx.bounds, factory, maximize=ctx.maximize, seed=ctx.seed, **opts)


def build_pigp(ctx: RunContext, *, kernel: str = "rbf", mean="f_inf", **bo_options) -> BayesOpt:
    r"""PI-GP Bayesian optimization: the kernel, mean and noise all come from ``ctx.prior``.

    The GP is built once at the prior's optimum here, so a bad ``kernel`` or ``mean`` raises
    before the first reading.

    Args:
        ctx: the run context.
        kernel: ``"rbf"`` (paper) or ``"rq"``.
        mean: ``"f_inf"`` (paper), ``"zero"`` (Fig. 2c) or a float.
        **bo_options: :class:`~pigp_torch.optimizers.BayesOpt` options over :data:`BO_DEFAULTS`.
    """
    prior = ctx.prior

    def factory(X, Y):
        return physics_informed_gp(X, Y, prior, kernel=kernel, mean=mean)

    factory(prior.x0[None], torch.tensor([[prior.f_x0]], dtype=DTYPE))
    return bayesopt(ctx, factory, bo_options)


def build_ml2(
    ctx: RunContext,
    *,
    refit_every: int = 1,
    noise: float | None = None,
    archive_spread: float = 0.2,
    learn_noise: bool = True,
    **bo_options,
) -> BayesOpt:
    r"""ML-II Bayesian optimization: diagonal ARD RBF with hyperparameters by marginal likelihood.

    With ``ctx.archive_size > 0`` (the benchmark) the hyperparameters are fitted first on an
    archive of ``ctx.archive_size`` readings of the machine (``ctx.archive``),
    then refitted on archive ∪ run data every ``refit_every`` asks (``0``: never refit). Without
    an archive (a live machine has none at hand) they are fitted on the run data every
    ``refit_every >= 1`` asks. Each refit is warm-started from the previous fit; between refits
    they are frozen. The GP itself is conditioned on the run data only.

    Args:
        ctx: the run context.
        refit_every: refit period in asks.
        noise: fixed noise standard deviation (``None``: learned, unless ``learn_noise`` is
            false).
        archive_spread: archive standard deviation as a fraction of the half-range.
        learn_noise: with ``noise=None``: learn the noise (default) or fix it to ``ctx.noise``.
        **bo_options: :class:`~pigp_torch.optimizers.BayesOpt` options over :data:`BO_DEFAULTS`.
    """
    refit_every = int(refit_every)
    archive = None
    if ctx.archive_size > 0:
        if refit_every < 0:
            raise ValueError(f"refit_every must be >= 0, got {refit_every}")
        if ctx.archive is None:
            raise ValueError("archive_size > 0 needs ctx.archive (readings of the machine)")
        archive = ctx.archive(ctx.archive_size, spread=archive_spread, seed=ctx.seed)
    elif refit_every < 1:
        raise ValueError(f"refit_every must be >= 1 (no archive to fit once), got {refit_every}")
    if noise is None and not learn_noise:
        noise = ctx.noise
    bounds = ctx.bounds
    state: dict[str, Any] = {"hyper": None, "calls": 0}

    def factory(X, Y):
        refit = state["hyper"] is None or (refit_every > 0 and state["calls"] % refit_every == 0)
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

    return bayesopt(ctx, factory, bo_options)
