r"""Neural-network surrogate :math:`\hat f(x)` of the simulated loss rate.

A smooth MLP (twice differentiable, so the prior can take its Hessian), its training with
validation split and early stopping, and pickle-free save/load.
"""

from pigp_torch.surrogate.ensemble import SurrogateEnsemble, train_ensemble
from pigp_torch.surrogate.io import load_surrogate, save_surrogate
from pigp_torch.surrogate.mlp import SurrogateMLP
from pigp_torch.surrogate.train import train_surrogate

__all__ = [
    "SurrogateEnsemble",
    "SurrogateMLP",
    "load_surrogate",
    "save_surrogate",
    "train_ensemble",
    "train_surrogate",
]
