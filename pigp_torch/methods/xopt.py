r"""Methods run through Xopt: stock Xopt UCB and Xopt UCB with the physics prior.

Xopt is the optional extra ``xopt``: each builder imports :mod:`pigp_torch.integrations.xopt`
when a run is built, so registering these methods does not need Xopt.

Methods (registered in :data:`~pigp_torch.methods.METHODS`):

* ``xopt-ucb`` — what an Xopt user would pick instead of pigp: Xopt 3's
  :class:`~xopt.generators.bayesian.UpperConfidenceBoundGenerator` with its defaults as
  constructed from the VOCS alone: ``beta = 2.0`` (:math:`\mu + \sqrt2\,\sigma`), the
  ``StandardModelConstructor`` GP (BoTorch ``SingleTaskGP``: ARD RBF kernel with BoTorch's
  dimension-scaled log-normal length-scale prior, inputs normalized to the VOCS box, outputs
  standardized, noise learned with a Gamma(1.1, 0.05) prior, all refitted by L-BFGS at every
  step on the run's data), acquisition optimized by ``LBFGSOptimizer`` (20 restarts from 20 raw
  samples, up to 1000 iterations), **no** ``max_travel_distances`` (Xopt's default: each step may
  go anywhere in the ±30 A box) and no TuRBO. Like every method it starts from the single
  skews-off reading (no random initial design: a control-room user starts from the machine's
  state). One deviation from the stock object: ``numerical_optimizer.max_time = None`` instead of
  5 s, so a run does not depend on the load of the computer (on a busy computer a wall-clock
  limit cuts the acquisition search short at random).
* ``xopt-ucb-travel`` — the same with ``max_travel_distances = 0.15`` of each knob's range (the
  safety limit Xopt/Badger users set on a machine; ±0.15 of the range is our trust box of ±0.3 of
  the half-range, but Xopt centres it on the LAST point, not the best one).
* ``xopt-tdbo`` — Xopt's time-dependent UCB (Kuklev et al., NAPAC 2022), the Xopt answer to a
  drifting machine: :class:`~pigp_torch.integrations.xopt_time.ReadingClockTDUCB`, a GP over the
  knobs and time (spectral-mixture kernel on time times an ARD Matérn 5/2 on the knobs, trained at
  every step) whose UCB (``beta = 2``) is maximised at the time of the next reading; time is the
  reading index (deterministic), every reading kept (``forgetting_time = None``); otherwise as
  ``xopt-ucb`` (no travel limit, ``max_time = None``).
* ``xopt-pigp`` — Xopt's UCB generator with
  :class:`~pigp_torch.integrations.xopt.PhysicsModelConstructor` (the physics prior's kernel, mean
  :math:`f_\infty` and noise, frozen), ``beta = 4`` (the authors' :math:`\mu + 2\sigma`) and
  ``max_travel_distances = 0.15``; otherwise Xopt defaults (same ``max_time = None``).
"""

from __future__ import annotations

from pigp_torch.methods.registry import RunContext

#: Fraction of each knob's full range per step for the travel-limited variants (= ±0.3 of the
#: half-range, the trust box of the native BO methods).
TRAVEL_FRACTION = 0.15


def _generator_kwargs(
    ctx: RunContext,
    beta: float,
    max_travel_distances: float | None,
    max_time: float | None,
    n_restarts: int,
) -> dict:
    from xopt.numerical_optimizer import LBFGSOptimizer

    kwargs = {
        "beta": float(beta),
        "numerical_optimizer": LBFGSOptimizer(n_restarts=int(n_restarts), max_time=max_time),
    }
    if max_travel_distances is not None:
        frac = float(max_travel_distances)
        if not frac > 0:
            raise ValueError(f"max_travel_distances must be positive, got {frac}")
        kwargs["max_travel_distances"] = [frac] * ctx.machine.dim
    return kwargs


def build_xopt_ucb(
    ctx: RunContext,
    *,
    beta: float = 2.0,
    max_travel_distances: float | None = None,
    max_time: float | None = None,
    n_restarts: int = 20,
    **generator_options,
):
    r"""Stock Xopt UCB (Xopt's default GP, trained at every step) as an ask/tell optimizer.

    Args:
        ctx: the run context (bounds and knob names from ``ctx.machine``).
        beta: UCB :math:`\beta` (Xopt default 2.0; BoTorch convention :math:`\mu +
            \sqrt\beta\,\sigma`).
        max_travel_distances: per-step limit as a fraction of each knob's full range, centred on
            the last point (Xopt's convention), or ``None`` (Xopt default: no limit).
        max_time: time limit of the acquisition optimization in seconds (Xopt default 5;
            ``None`` here for load-independent runs).
        n_restarts: L-BFGS restarts (Xopt default 20).
        **generator_options: further ``UpperConfidenceBoundGenerator`` fields.
    """
    from xopt.generators.bayesian import UpperConfidenceBoundGenerator

    from pigp_torch.integrations.xopt import XoptOptimizer, vocs_from_bounds

    vocs = vocs_from_bounds(ctx.machine.knob_names, ctx.bounds)
    kwargs = _generator_kwargs(ctx, beta, max_travel_distances, max_time, n_restarts)
    gen = UpperConfidenceBoundGenerator(vocs=vocs, **kwargs, **generator_options)
    return XoptOptimizer(gen, seed=ctx.seed)


def build_xopt_pigp(
    ctx: RunContext,
    *,
    beta: float = 4.0,
    max_travel_distances: float | None = TRAVEL_FRACTION,
    max_time: float | None = None,
    n_restarts: int = 20,
    kernel: str = "rbf",
    mean="f_inf",
    **generator_options,
):
    r"""Xopt UCB with the physics-informed GP
    (:class:`~pigp_torch.integrations.xopt.PhysicsModelConstructor`).

    Args:
        ctx: the run context (``ctx.prior`` gives kernel, mean and noise).
        beta: UCB :math:`\beta` (default 4: the authors' :math:`\mu + 2\sigma`).
        max_travel_distances: per-step limit (fraction of the full range, centred on the last
            point) or ``None``.
        max_time, n_restarts: as in :func:`build_xopt_ucb`.
        kernel: ``"rbf"`` or ``"rq"``.
        mean: ``"f_inf"``, ``"zero"`` or a float.
        **generator_options: further ``UpperConfidenceBoundGenerator`` fields.
    """
    from xopt.generators.bayesian import UpperConfidenceBoundGenerator

    from pigp_torch.integrations.xopt import (
        PhysicsModelConstructor,
        XoptOptimizer,
        vocs_from_bounds,
    )

    vocs = vocs_from_bounds(ctx.machine.knob_names, ctx.bounds)
    kwargs = _generator_kwargs(ctx, beta, max_travel_distances, max_time, n_restarts)
    constructor = PhysicsModelConstructor(prior=ctx.prior, kernel=kernel, mean=mean)
    gen = UpperConfidenceBoundGenerator(
        vocs=vocs, gp_constructor=constructor, **kwargs, **generator_options
    )
    return XoptOptimizer(gen, seed=ctx.seed)


def build_xopt_tdbo(
    ctx: RunContext,
    *,
    beta: float = 2.0,
    added_time: float = 1.0,
    forgetting_time: float | None = None,
    max_travel_distances: float | None = None,
    max_time: float | None = None,
    n_restarts: int = 20,
    **generator_options,
):
    r"""Xopt's time-dependent UCB on the reading clock as an ask/tell optimizer.

    Args:
        ctx: the run context (bounds, knob names and direction from ``ctx``).
        beta: UCB :math:`\beta` (Xopt default 2.0).
        added_time: readings from the last reading to the target time of a proposal (default 1:
            the next reading).
        forgetting_time: readings of memory (``None``, default: all).
        max_travel_distances, max_time, n_restarts: as in :func:`build_xopt_ucb`.
        **generator_options: further ``TDUpperConfidenceBoundGenerator`` fields.
    """
    from pigp_torch.integrations.xopt import XoptOptimizer, vocs_from_bounds
    from pigp_torch.integrations.xopt_time import ReadingClockTDUCB

    vocs = vocs_from_bounds(ctx.machine.knob_names, ctx.bounds, maximize=ctx.maximize)
    kwargs = _generator_kwargs(ctx, beta, max_travel_distances, max_time, n_restarts)
    gen = ReadingClockTDUCB(
        vocs=vocs,
        added_time=added_time,
        forgetting_time=forgetting_time,
        **kwargs,
        **generator_options,
    )
    return XoptOptimizer(gen, seed=ctx.seed)
