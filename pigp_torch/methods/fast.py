r"""The PI-GP method on :class:`~pigp_torch.optimizers.fast_bo.FastBayesOpt` (``pigp-fast``)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from pigp_torch.methods.gp import BO_DEFAULTS
from pigp_torch.methods.registry import RunContext
from pigp_torch.optimizers.fast_bo import FastBayesOpt


def fast_bo_options(options: Mapping[str, Any]) -> dict:
    """:class:`FastBayesOpt` options: ``options`` over the :data:`BO_DEFAULTS` it shares with
    :class:`BayesOpt` (acquisition, beta, step_limit, trust_center); its search keeps its own."""
    keys = ("acquisition", "beta", "step_limit", "trust_center")
    return {**{k: BO_DEFAULTS[k] for k in keys}, **options}


def build_pigp_fast(ctx: RunContext, *, mean="f_inf", **options) -> FastBayesOpt:
    r"""The ``"pigp"`` method on :class:`~pigp_torch.optimizers.fast_bo.FastBayesOpt`: the same
    fixed-kernel GP posterior (incremental Cholesky) and acquisition, :data:`BO_DEFAULTS` for
    ``acquisition``, ``beta``, ``step_limit`` and ``trust_center``, its own batched Newton
    acquisition search (:class:`FastBayesOpt`'s defaults: 10 Newton restarts from the best of 256
    random points plus the trust-box centre and the last two proposals)."""
    return FastBayesOpt.from_prior(
        ctx.bounds,
        ctx.prior,
        mean=mean,
        seed=ctx.seed,
        **fast_bo_options(options),
    )
