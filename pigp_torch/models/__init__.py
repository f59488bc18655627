"""Models and posteriors: the physics-informed GP, the data-informed (ML-II) comparison GP, the
online-fitted physics form of the loss rate, and the posteriors of the Bayesian-optimization core
(:mod:`~pigp_torch.models.posterior`)."""

from pigp_torch.models.inverse_sqrt import InverseSqrtPeakModel
from pigp_torch.models.ml2 import ml2_gp
from pigp_torch.models.physics_informed import physics_informed_gp

__all__ = [
    "InverseSqrtPeakModel",
    "ml2_gp",
    "physics_informed_gp",
]
