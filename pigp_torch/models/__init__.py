"""GP model builders: the physics-informed GP and the data-informed (ML-II) comparison GP."""

from pigp_torch.models.ml2 import ml2_gp
from pigp_torch.models.physics_informed import physics_informed_gp
from pigp_torch.models.physics_mean import PhysicsMean, fit_physics_mean

__all__ = ["PhysicsMean", "fit_physics_mean", "ml2_gp", "physics_informed_gp"]
