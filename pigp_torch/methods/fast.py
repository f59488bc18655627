r"""The PI-GP method on :class:`~pigp_torch.optimizers.fast_bo.FastBayesOpt` (``pigp-fast``)."""

from __future__ import annotations

from pigp_torch.methods.registry import RunContext
from pigp_torch.optimizers.fast_bo import FastBayesOpt


def build_pigp_fast(ctx: RunContext, *, mean="f_inf", **options) -> FastBayesOpt:
    r"""The ``"pigp"`` method on :class:`~pigp_torch.optimizers.fast_bo.FastBayesOpt`: the same
    fixed-kernel GP posterior (incremental Cholesky) and acquisition with the shared defaults
    (:data:`~pigp_torch.optimizers.bo.defaults.BO_DEFAULTS`: ``acquisition``, ``beta``,
    ``step_limit``, ``trust_center``), its own batched Newton acquisition search
    (:data:`~pigp_torch.optimizers.bo.defaults.NEWTON_SEARCH_DEFAULTS`); ``options`` override
    them."""
    return FastBayesOpt.from_prior(ctx.bounds, ctx.prior, mean=mean, seed=ctx.seed, **options)
