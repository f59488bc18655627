r"""Methods of the ARES-EA task (DESY linac, five magnets, one screen).

* ``published-bo``: the published BO recipe (:class:`~pigp_torch.optimizers.ares_published.
  PublishedAresBO`): unidirectional quadrupoles, knobs scaled to [−3, 3], the start and 4 uniform
  samples in a ±0.3 box around it, then SingleTaskGP + EI + ``optimize_acqf`` in the ±0.3 box
  around the last sample; maximizes the machine's ``"reward"`` objective.
* ``published-nm``: the published Nelder–Mead recipe on the project's
  :class:`~pigp_torch.optimizers.NelderMead`: bidirectional quadrupoles, classical coefficients,
  initial simplex steps of a quarter of each knob's range (±0.5 on knobs scaled to [−1, 1]), from
  the same start; minimizes the machine's ``"distance"`` objective (MAE, 100× off the screen). The
  published run minimized the step-to-step change of that distance (a "differential" reward); here
  the distance itself is minimized, which makes the objective stationary.

:data:`ARES_METHOD_OBJECTIVE` says which machine objective (:data:`~pigp_torch.machine.ares.
ARES_OBJECTIVES`) each method reads; a method not listed reads ``"reward"``.
"""

from __future__ import annotations

import torch

from pigp_torch._utils import DTYPE
from pigp_torch.methods.registry import RunContext
from pigp_torch.optimizers import NelderMead
from pigp_torch.optimizers.ares_published import PublishedAresBO
from pigp_torch.simulation.ares import START_SETTING, knob_bounds

#: The machine objective each ARES method reads (``read()`` of
#: :class:`~pigp_torch.machine.ares.AresMachine`).
ARES_METHOD_OBJECTIVE: dict[str, str] = {
    "published-bo": "reward",
    "published-nm": "distance",
    "ares-physics": "mae",
}


def ares_objective_for(method: str) -> str:
    """The machine objective method ``method`` reads (default ``"reward"``)."""
    return ARES_METHOD_OBJECTIVE.get(method, "reward")


def build_published_bo(ctx: RunContext, *, unidirectional: bool = True, **options):
    """The published BO recipe; ``unidirectional`` restricts the quadrupoles as published
    (Q1 ≥ 0, Q2 ≤ 0, Q3 ≥ 0) within the machine's bounds."""
    bounds = ctx.bounds
    if unidirectional:
        uni = knob_bounds(unidirectional=True)
        bounds = torch.stack([torch.maximum(bounds[0], uni[0]), torch.minimum(bounds[1], uni[1])])
    x0 = torch.tensor(START_SETTING, dtype=DTYPE)
    return PublishedAresBO(bounds, x0=x0, seed=ctx.seed, maximize=ctx.maximize, **options)


def build_published_nm(ctx: RunContext, *, initial_simplex_size: float = 0.25, **options):
    """The published Nelder–Mead recipe (classical coefficients, a quarter-range simplex)."""
    options.setdefault("adaptive", False)
    return NelderMead(
        ctx.bounds, initial_simplex_size=initial_simplex_size, maximize=ctx.maximize, **options
    )
