r"""The physics form fitted online (``pigp-physics``):
:class:`~pigp_torch.optimizers.physics_bo.PhysicsModelBO`."""

from __future__ import annotations

from pigp_torch.methods.registry import RunContext
from pigp_torch.optimizers.physics_bo import PhysicsModelBO


def build_pigp_physics(ctx: RunContext, **options) -> PhysicsModelBO:
    r"""UCB on the online-fitted physics form :math:`f_\infty + (c + \beta(\mathbf x -
    \boldsymbol\mu)^\top B(\mathbf x - \boldsymbol\mu))^{-1/2}`, :math:`B` from ``ctx.prior``
    (:class:`~pigp_torch.optimizers.physics_bo.PhysicsModelBO`; ``options`` override its
    defaults; the noise is ``ctx.noise`` when known, else the model's default)."""
    if ctx.noise is not None:
        options = {"noise": ctx.noise, **options}
    return PhysicsModelBO(ctx.bounds, ctx.prior, seed=ctx.seed, **options)
