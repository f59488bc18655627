r"""A reference, not a product method: ``pigp-physics`` told each machine's own physics.

:data:`ORACLE` builds :class:`~pigp_torch.optimizers.PhysicsModelBO` with the prior of the
machine under test instead of the model ring's: the shape :math:`B` of its own peak
(:func:`~pigp_torch.simulation.ensemble.ensemble_optima` of the machine itself), its own
background :math:`f_\infty` and peak height :math:`f(\boldsymbol\mu)` (so the prior on
:math:`\log c` is centred on the truth), and the model's prior on where the centre lies (the
centre itself stays unknown). The gap between it and ``pigp-physics`` on the same machines is
what the model's prior costs.
"""

from __future__ import annotations

import dataclasses

from pigp_torch.methods import MethodSpec, RunContext
from pigp_torch.optimizers.physics_bo import PhysicsModelBO
from pigp_torch.simulation.ensemble import ensemble_optima


def oracle_prior(ctx: RunContext):
    """The prior of ``ctx`` with the machine's own shape, background and peak height."""
    sim = ctx.machine.sim
    opt = ensemble_optima([sim.error_seed], model=sim)
    if opt.failed:
        raise RuntimeError(f"no optimum found for the oracle of machine {sim.error_seed}")
    mu, B = opt.centers[0], opt.shapes[0]
    f_inf = float(sim.loss_background)
    f_mu = float(sim.loss_rate(mu))
    c = (f_mu - f_inf) ** -2
    return dataclasses.replace(ctx.prior, f_inf=f_inf, f_x0=f_mu, peak_shape=B,
                               precision=B / (2 * c))  # fmt: skip


def build_oracle(ctx: RunContext, **options) -> PhysicsModelBO:
    """``pigp-physics`` (same defaults) with :func:`oracle_prior`."""
    prior = oracle_prior(ctx)
    return PhysicsModelBO(ctx.bounds, prior, seed=ctx.seed, noise=ctx.noise, **options)


#: The oracle reference (budget class ``"gp"``, reads the prior's centre covariance).
ORACLE = MethodSpec("pigp-physics-oracle", build_oracle, "gp", {}, True)
