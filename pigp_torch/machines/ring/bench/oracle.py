r"""A reference, not a product method: ``pigp-physics`` told each machine's own physics.

:data:`ORACLE` builds :class:`~pigp_torch.optimizers.PhysicsModelBO` with the prior of the
machine under test instead of the model ring's: the shape :math:`B` of its own peak
(:func:`machine_peak`: the unconstrained optimum of the machine itself), its own
background :math:`f_\infty` and peak height :math:`f(\boldsymbol\mu)` (so the prior on
:math:`\log c` is centred on the truth), and the model's prior on where the centre lies (the
centre itself stays unknown). The gap between it and ``pigp-physics`` on the same machines is
what the model's prior costs. It reads the machine from the run (``ctx.machine.sim``), so it
works on either machine family (:mod:`~.families`).
"""

from __future__ import annotations

import dataclasses

from pigp_torch.machines.ring.ensemble import unconstrained_optimum
from pigp_torch.methods import MethodSpec, RunContext
from pigp_torch.optimizers.physics_bo import PhysicsModelBO


def machine_peak(sim):
    r"""``(mu, B)``: the unconstrained optimum :math:`\boldsymbol\mu` (``K``, control units)
    of the loss rate of the machine ``sim`` itself and the peak's shape :math:`B` there
    (``K x K``; :func:`~pigp_torch.machines.ring.ensemble.unconstrained_optimum`, search boxes up
    to 4 knob boxes). Searched on ``sim`` as built (not rebuilt from its error seed, which
    would lose a wide machine's re-tuned lattice and drawn error scale).

    Raises:
        RuntimeError: no optimum found.
    """
    try:
        mu, _, B = unconstrained_optimum(sim, 4.0)
    except (RuntimeError, ValueError) as err:
        raise RuntimeError(f"no optimum found for machine {sim.error_seed}: {err}") from err
    return mu, B


def oracle_prior(ctx: RunContext):
    """The prior of ``ctx`` with the machine's own shape, background and peak height."""
    sim = ctx.machine.sim
    mu, B = machine_peak(sim)
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
