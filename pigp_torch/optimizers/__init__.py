"""Ask/tell optimizers: the Bayesian-optimization core and its recipes, Nelder–Mead, RCDS.

The methods by name (run files, the benchmark, the CLI) are the one registry
:data:`pigp_torch.methods.METHODS`.
"""

from pigp_torch.optimizers.base import AskTellOptimizer, check_bounds
from pigp_torch.optimizers.bayesopt import BayesOpt
from pigp_torch.optimizers.bo import BayesianOptimizer, BOParts
from pigp_torch.optimizers.fast_bo import FastBayesOpt
from pigp_torch.optimizers.nelder_mead import NelderMead
from pigp_torch.optimizers.physics_bo import PhysicsModelBO
from pigp_torch.optimizers.rcds import RCDS

__all__ = [
    "RCDS",
    "AskTellOptimizer",
    "BOParts",
    "BayesOpt",
    "BayesianOptimizer",
    "FastBayesOpt",
    "NelderMead",
    "PhysicsModelBO",
    "check_bounds",
]
