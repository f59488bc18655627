"""GP model builders: the physics-informed GP, the data-informed (ML-II) comparison GP, and the
online-fitted physics form of the loss rate."""

from pigp_torch.models.inverse_sqrt import InverseSqrtPeakModel
from pigp_torch.models.ml2 import ml2_gp
from pigp_torch.models.physics_informed import physics_informed_gp
from pigp_torch.models.physics_mean import PhysicsMean, fit_physics_mean

__all__ = [
    "InverseSqrtPeakModel",
    "PhysicsMean",
    "fit_physics_mean",
    "ml2_gp",
    "physics_informed_gp",
]
