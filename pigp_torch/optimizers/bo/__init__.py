r"""The Bayesian-optimization core: :class:`BayesianOptimizer` and its parts.

A method is a recipe of four parts (:class:`BOParts`): a posterior
(:mod:`pigp_torch.models.posterior`), an acquisition (:mod:`.acquisition`), a search
(:mod:`.search`) and a region (:mod:`.region`). ``BayesOpt``, ``FastBayesOpt`` and
``PhysicsModelBO`` are such recipes.
"""

from pigp_torch.optimizers.bo.acquisition import (
    EI,
    UCB,
    Alternating,
    BoTorchAcquisition,
    CentreInformation,
    CorrelatedCentreInformation,
    ExpectedCentreInformation,
    LogEI,
    Schedule,
    WhileDrifting,
    analytic,
    botorch_analytic,
)
from pigp_torch.optimizers.bo.core import BayesianOptimizer, BOParts
from pigp_torch.optimizers.bo.region import TrustRegion, trust_box
from pigp_torch.optimizers.bo.search import MultiStartLBFGSB, NewtonSearch, OptimizeAcqf

__all__ = [
    "EI",
    "UCB",
    "Alternating",
    "BOParts",
    "BayesianOptimizer",
    "BoTorchAcquisition",
    "CentreInformation",
    "CorrelatedCentreInformation",
    "ExpectedCentreInformation",
    "LogEI",
    "MultiStartLBFGSB",
    "NewtonSearch",
    "OptimizeAcqf",
    "Schedule",
    "TrustRegion",
    "WhileDrifting",
    "analytic",
    "botorch_analytic",
    "trust_box",
]
