"""Ask/tell optimizers: Bayesian optimization, Nelder–Mead, RCDS; ``OPTIMIZERS`` by name."""

from pigp_torch.optimizers.base import AskTellOptimizer, check_bounds
from pigp_torch.optimizers.bayesopt import BayesOpt
from pigp_torch.optimizers.fast_bo import FastBayesOpt
from pigp_torch.optimizers.nelder_mead import NelderMead
from pigp_torch.optimizers.physics_bo import PhysicsModelBO
from pigp_torch.optimizers.rcds import RCDS

#: The generic optimizer classes by their ``name`` (the methods that run files, the benchmark and
#: the CLI name are in :mod:`pigp_torch.methods`).
OPTIMIZERS = {
    BayesOpt.name: BayesOpt,
    NelderMead.name: NelderMead,
    RCDS.name: RCDS,
}

__all__ = [
    "OPTIMIZERS",
    "RCDS",
    "AskTellOptimizer",
    "BayesOpt",
    "FastBayesOpt",
    "NelderMead",
    "PhysicsModelBO",
    "check_bounds",
]
