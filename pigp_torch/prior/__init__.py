"""Physics prior of the PI-GP: optimum search, Hessian of log(f - f_inf), repair, save/load."""

from pigp_torch.prior.build import prior_from_model
from pigp_torch.prior.hessian import (
    finite_difference_hessian,
    log_excess_hessian,
    repair_negative_definite,
)
from pigp_torch.prior.optimum import find_optimum
from pigp_torch.prior.physics_prior import PhysicsPrior

__all__ = [
    "PhysicsPrior",
    "find_optimum",
    "finite_difference_hessian",
    "log_excess_hessian",
    "prior_from_model",
    "repair_negative_definite",
]
