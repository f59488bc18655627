"""The optimum x0 of a model: multi-start L-BFGS-B (shared with the simulator's true optimum)."""

from pigp_torch._utils import check_bounds
from pigp_torch._utils.multistart import find_optimum

__all__ = ["check_bounds", "find_optimum"]
