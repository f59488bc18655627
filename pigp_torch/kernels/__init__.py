"""GPyTorch kernels with a full, fixed precision matrix (one kernel per file)."""

from pigp_torch.kernels.full_precision_rbf import FullPrecisionRBFKernel
from pigp_torch.kernels.full_precision_rq import FullPrecisionRQKernel

__all__ = ["FullPrecisionRBFKernel", "FullPrecisionRQKernel"]
