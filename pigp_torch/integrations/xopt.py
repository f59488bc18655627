r"""Physics priors inside Xopt / Badger, and Xopt generators as ask/tell optimizers.

Needs the optional extra ``xopt`` (``pip install "pigp-torch[xopt]"``). The VOCS and data-frame
helpers are in :mod:`~pigp_torch.integrations.xopt_vocs`, the physics GP and its model
constructor in :mod:`~pigp_torch.integrations.xopt_gp`; this module adds the ask/tell
front end and names them all.

**Ask/tell.** :class:`XoptOptimizer` drives any single-objective Xopt generator (e.g.
:class:`~xopt.generators.bayesian.UpperConfidenceBoundGenerator`) through ``tell`` ->
``generator.add_data`` and ``ask`` -> ``generator.generate(1)``, so :func:`pigp_torch.optimize`
and the benchmark can run stock Xopt next to our own optimizers.

Security note: Xopt's pydantic models ``torch.load`` (unpickle) any string field that names an
existing ``*.pt`` file when they are validated; build generators from trusted configurations only.
"""

from __future__ import annotations

import pandas as pd
import torch

from pigp_torch._utils import DTYPE
from pigp_torch.integrations.xopt_gp import PhysicsModelConstructor, physics_vocs_gp
from pigp_torch.integrations.xopt_vocs import (
    XOPT_ERROR,
    XOPT_RUNTIME,
    continuous_bounds,
    prior_as_dict,
    single_objective,
    to_xopt_dataframe,
    vocs_from_bounds,
    vocs_from_prior,
)
from pigp_torch.optimizers.base import AskTellOptimizer

__all__ = [
    "XOPT_ERROR",
    "XOPT_RUNTIME",
    "PhysicsModelConstructor",
    "XoptOptimizer",
    "physics_vocs_gp",
    "prior_as_dict",
    "to_xopt_dataframe",
    "vocs_from_bounds",
    "vocs_from_prior",
]


# ----------------------------------------------------------------------------- ask/tell
class XoptOptimizer(AskTellOptimizer):
    r"""Any single-objective Xopt generator behind the ask/tell protocol.

    ``tell(x, y)`` appends one row (variables, VOCS constants, objective) to the generator's data
    (``generator.add_data``); ``ask()`` calls ``generator.generate(1)`` and returns the candidate
    as a ``d`` tensor in the order of ``vocs.variable_names`` (= ``knob_names``). The direction
    comes from the VOCS (``MAXIMIZE`` / ``MINIMIZE``). The candidate is clamped into the VOCS
    bounds as a last guard against round-off (a machine refuses a setting outside its bounds).

    Determinism: each ask runs under a forked torch RNG seeded with ``seed + n_told`` (Xopt's
    acquisition optimizer draws its random restarts from the global torch RNG; the global state is
    left untouched). Xopt's ``LBFGSOptimizer`` stops at ``max_time`` seconds (default 5), which
    can make a run depend on the machine's load; set ``numerical_optimizer.max_time=None`` for
    reproducible runs.

    After each ask, ``last_info`` holds Xopt's timings (``training``,
    ``acquisition_optimization``, seconds) and ``n_train``.

    Args:
        generator: an Xopt generator with ``vocs``, ``add_data`` and ``generate`` (e.g.
            ``UpperConfidenceBoundGenerator(vocs=...)``); its variables must be continuous.
        seed: base seed of the per-ask RNG.

    Raises:
        ValueError: a VOCS with other than one MAXIMIZE/MINIMIZE objective, or non-continuous
            variables.
    """

    name = "xopt"

    def __init__(self, generator, *, seed: int = 0) -> None:
        for attr in ("vocs", "add_data", "generate"):
            if not hasattr(generator, attr):
                raise ValueError(f"generator has no attribute {attr!r}: not an Xopt generator")
        vocs = generator.vocs
        objective, maximize = single_objective(vocs)
        super().__init__(continuous_bounds(vocs), maximize=maximize)
        self.generator = generator
        self.vocs = vocs
        self.objective = objective
        self.knob_names = list(vocs.variable_names)
        self.seed = int(seed)
        self.name = f"xopt-{getattr(generator, 'name', 'generator')}"
        self.last_info: dict = {}

    def tell(self, x, y: float) -> None:
        """Record ``y`` at ``x`` here and in the generator's data."""
        super().tell(x, y)
        row = dict(zip(self.knob_names, self.X[-1].tolist(), strict=True))
        row.update({k: v.value for k, v in self.vocs.constants.items()})
        row[self.objective] = self.Y[-1]
        self.generator.add_data(pd.DataFrame([row]))

    def ask(self) -> torch.Tensor:
        """``generator.generate(1)`` as a ``d`` float64 tensor inside the bounds."""
        if not self.Y:
            raise RuntimeError("no measurements yet: tell() the start point first")
        with torch.random.fork_rng():
            torch.manual_seed(self.seed + self.n_told)
            candidates = self.generator.generate(1)
        if len(candidates) != 1:
            raise RuntimeError(f"generator returned {len(candidates)} candidates, expected 1")
        x = torch.tensor([float(candidates[0][n]) for n in self.knob_names], dtype=DTYPE)
        if not torch.isfinite(x).all():
            raise RuntimeError(f"generator proposed a non-finite setting {x.tolist()}")
        x = torch.minimum(torch.maximum(x, self.bounds[0]), self.bounds[1])
        timing = getattr(self.generator, "computation_time", None)
        info = {"n_train": self.n_told}
        if isinstance(timing, pd.DataFrame) and len(timing):
            info.update({k: float(v) for k, v in timing.iloc[-1].items()})
        self.last_info = info
        return x
