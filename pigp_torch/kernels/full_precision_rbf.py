r"""Squared-exponential kernel with a full, fixed precision matrix (the paper's PI-GP kernel)."""

from __future__ import annotations

from torch import Tensor

from pigp_torch.kernels._base import FullPrecisionKernelBase


class FullPrecisionRBFKernel(FullPrecisionKernelBase):
    r"""RBF kernel with a full, fixed precision matrix :math:`P`.

    .. math::
        k(\mathbf x, \mathbf x') = \exp\!\left(-\tfrac12 (\mathbf x - \mathbf x')^\top P
        (\mathbf x - \mathbf x')\right)

    :math:`P` is a PRECISION (inverse squared length, units 1 / knob²), not a covariance: along an
    eigenvector of :math:`P` with eigenvalue :math:`\lambda` the correlation length is
    :math:`1/\sqrt{\lambda}`, so a stiff direction of the objective (large curvature) gets a SHORT
    correlation length. In the physics-informed GP, :math:`P = \Sigma = -H/2` with :math:`H` the
    Hessian of :math:`\log(f - f_\infty)` at the optimum.

    :math:`P` is stored as its Cholesky factor :math:`L` (buffer ``precision_cholesky``,
    :math:`P = L L^\top`) and :math:`q` is computed as the squared distance between
    :math:`\mathbf x L` and :math:`\mathbf x' L`. The kernel has no trainable parameters; wrap it
    in :class:`~gpytorch.kernels.ScaleKernel` for the amplitude :math:`\sigma_f^2`.

    Args:
        precision: ``d x d`` symmetric positive-definite matrix :math:`P`.
        **kwargs: passed to :class:`gpytorch.kernels.Kernel`.

    Example:
        >>> import torch
        >>> k = FullPrecisionRBFKernel(torch.tensor([[4.0, 1.0], [1.0, 2.0]]))
        >>> K = k(torch.randn(5, 2, dtype=torch.float64)).to_dense()  # 5 x 5
    """

    def _profile(self, q: Tensor) -> Tensor:
        return q.mul(-0.5).exp()
