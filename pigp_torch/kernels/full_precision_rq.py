r"""Heavy-tailed rational-quadratic kernel with a full, fixed precision matrix."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from pigp_torch.kernels._base import FullPrecisionKernelBase


class FullPrecisionRQKernel(FullPrecisionKernelBase):
    r"""Rational-quadratic kernel with a full, fixed precision matrix :math:`P`.

    .. math::
        k(\mathbf x, \mathbf x') = \left(1 + \frac{q}{2\alpha}\right)^{-\alpha}, \qquad
        q = (\mathbf x - \mathbf x')^\top P (\mathbf x - \mathbf x').

    Why: the vertical emittance is quadratic in the skew strengths, so the Touschek loss rate falls
    like :math:`F/\sqrt{1 + q}` away from the optimum — a power-law tail, much heavier than a
    Gaussian's. With :math:`\alpha = 1/2` this kernel is :math:`(1 + q)^{-1/2}`, the same tail.
    Near :math:`q = 0` it agrees with :class:`FullPrecisionRBFKernel` to first order
    (:math:`k \approx 1 - q/2`), so :math:`P` keeps its meaning as the curvature (precision) of
    the correlation; and for :math:`\alpha \to \infty` it tends to the RBF
    :math:`\exp(-q/2)` (it is a scale mixture of RBFs with a Gamma-distributed precision scale).

    :math:`P` is stored as its Cholesky factor (buffer ``precision_cholesky``) and :math:`\alpha`
    as a buffer ``alpha``: nothing is trainable.

    Args:
        precision: ``d x d`` symmetric positive-definite matrix :math:`P` (1 / knob²).
        alpha: shape :math:`\alpha > 0` (tail exponent); default 0.5.
        **kwargs: passed to :class:`gpytorch.kernels.Kernel`.
    """

    def __init__(self, precision, alpha: float = 0.5, **kwargs):
        super().__init__(precision, **kwargs)
        alpha = float(alpha)
        if not (math.isfinite(alpha) and alpha > 0):
            raise ValueError(f"alpha must be a finite positive number, got {alpha}")
        self.register_buffer("alpha", torch.tensor(alpha, dtype=torch.float64))

    def _profile(self, q: Tensor) -> Tensor:
        alpha = self.alpha.to(dtype=q.dtype, device=q.device)
        # log1p keeps (1 + q / 2a)^(-a) accurate for large alpha (the RBF limit).
        return torch.exp(-alpha * torch.log1p(q / (2.0 * alpha)))
