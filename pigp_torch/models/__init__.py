"""GP model builders: the physics-informed GP and the data-informed (ML-II) comparison GP."""

from pigp_torch.models.ml2 import ml2_gp
from pigp_torch.models.physics_informed import physics_informed_gp

__all__ = ["ml2_gp", "physics_informed_gp"]
