r"""Shared machinery of the full-precision stationary kernels.

Both kernels of this package depend on the inputs only through the quadratic form

.. math::
    q(\mathbf x, \mathbf x') = (\mathbf x - \mathbf x')^\top P \, (\mathbf x - \mathbf x')
    = \lVert (\mathbf x - \mathbf x')^\top L \rVert^2, \qquad P = L L^\top,

with a fixed symmetric positive-definite precision matrix :math:`P` (units: 1 / knob²). The
Cholesky factor :math:`L` is validated once and stored as a registered buffer, so it follows
``.to(device)`` and ``state_dict`` but is never trained.
"""

from __future__ import annotations

import torch
from gpytorch.kernels import Kernel
from torch import Tensor

#: Relative tolerance for the symmetry check, ``max|P - P^T| <= SYMMETRY_RTOL * max|P|``.
SYMMETRY_RTOL = 1e-8


def precision_cholesky(precision) -> Tensor:
    r"""Validate a precision matrix and return its lower Cholesky factor in float64.

    Args:
        precision: ``d x d`` symmetric positive-definite matrix :math:`P`.

    Returns:
        ``d x d`` lower-triangular :math:`L` with :math:`P = L L^\top` (of the symmetrized
        :math:`(P + P^\top)/2`).

    Raises:
        ValueError: not a square 2-D matrix, non-finite entries, not symmetric to
            :data:`SYMMETRY_RTOL`, or not positive definite.
    """
    # Python lists straight to float64 (as_tensor would round them through float32)
    P = (
        precision
        if isinstance(precision, Tensor)
        else torch.as_tensor(precision, dtype=torch.float64)
    )
    P = P.detach().to(torch.float64)
    if P.dim() != 2 or P.shape[0] != P.shape[1] or P.shape[0] == 0:
        raise ValueError(f"precision must be a non-empty square d x d matrix, got {tuple(P.shape)}")
    if not torch.isfinite(P).all():
        raise ValueError("precision contains NaN or inf")
    asym = (P - P.T).abs().max().item()
    scale = P.abs().max().item()
    if asym > SYMMETRY_RTOL * scale:
        raise ValueError(
            f"precision must be symmetric: max|P - P^T| = {asym:.3g} exceeds "
            f"{SYMMETRY_RTOL:g} * max|P| = {SYMMETRY_RTOL * scale:.3g}"
        )
    P = 0.5 * (P + P.T)
    L, info = torch.linalg.cholesky_ex(P)
    if info.item() != 0:
        eig_min = torch.linalg.eigvalsh(P).min().item()
        raise ValueError(
            f"precision must be positive definite; smallest eigenvalue is {eig_min:.3g}"
        )
    return L


class FullPrecisionKernelBase(Kernel):
    r"""Base class: a stationary kernel that is a function of :math:`q = \delta^\top P \delta`.

    Subclasses implement :meth:`_profile`, the map :math:`q \mapsto k`. The class has no
    trainable parameters; wrap it in a :class:`~gpytorch.kernels.ScaleKernel` for an amplitude.

    Args:
        precision: ``d x d`` symmetric positive-definite precision matrix :math:`P`.
        **kwargs: passed to :class:`gpytorch.kernels.Kernel` (e.g. ``active_dims``).
    """

    has_lengthscale = False

    def __init__(self, precision, **kwargs):
        super().__init__(**kwargs)
        self.register_buffer("precision_cholesky", precision_cholesky(precision))

    @property
    def is_stationary(self) -> bool:
        return True

    @property
    def dim(self) -> int:
        """Number of input dimensions ``d``."""
        return self.precision_cholesky.shape[-1]

    @property
    def precision(self) -> Tensor:
        r"""The ``d x d`` precision matrix :math:`P = L L^\top` (dtype of the buffer: float64
        unless the module was cast)."""
        L = self.precision_cholesky
        return L @ L.transpose(-1, -2)

    def quadratic_form(self, x1: Tensor, x2: Tensor, diag: bool = False) -> Tensor:
        r"""Squared Mahalanobis distances :math:`q_{ij} = (x_{1,i} - x_{2,j})^\top P (\dots)`.

        Args:
            x1: ``batch_shape x n x d`` inputs.
            x2: ``batch_shape x m x d`` inputs.
            diag: if True return only :math:`q_{ii}` (needs ``n == m``).

        Returns:
            ``batch_shape x n x m`` (or ``batch_shape x n`` with ``diag``) tensor, dtype of ``x1``.
        """
        d = self.dim
        if x1.shape[-1] != d or x2.shape[-1] != d:
            raise ValueError(
                f"inputs must have last dimension {d} (the precision's size); "
                f"got x1 {tuple(x1.shape)}, x2 {tuple(x2.shape)}"
            )
        L = self.precision_cholesky.to(dtype=x1.dtype, device=x1.device)
        return self.covar_dist(x1 @ L, x2 @ L, diag=diag, square_dist=True)

    def _profile(self, q: Tensor) -> Tensor:  # pragma: no cover - abstract
        raise NotImplementedError

    def forward(self, x1: Tensor, x2: Tensor, diag: bool = False, **params) -> Tensor:
        if params.get("last_dim_is_batch", False):
            raise ValueError(f"{type(self).__name__} does not support last_dim_is_batch")
        return self._profile(self.quadratic_form(x1, x2, diag=diag))
