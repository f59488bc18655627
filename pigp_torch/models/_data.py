"""Validation of training data shared by the GP builders."""

from __future__ import annotations

import torch
from torch import Tensor

from pigp_torch._utils import DTYPE, as_knob_tensor


def training_data(X, Y, dim: int, *, name: str = "") -> tuple[Tensor, Tensor]:
    r"""Validate GP training data.

    Args:
        X: ``n x dim`` knob settings (a single point of shape ``dim`` is NOT accepted).
        Y: ``n`` or ``n x 1`` observations.
        dim: number of knobs.
        name: prefix for error messages (e.g. ``"archive "``).

    Returns:
        ``(X, Y)`` as float64 tensors of shapes ``n x dim`` and ``n x 1``.
    """
    if not isinstance(X, Tensor):
        X = torch.as_tensor(X, dtype=DTYPE)
    if not isinstance(Y, Tensor):
        Y = torch.as_tensor(Y, dtype=DTYPE)
    if X.dim() != 2:
        raise ValueError(f"{name}X must have shape (n, {dim}), got {tuple(X.shape)}")
    X, _ = as_knob_tensor(X, dim, name=f"{name}X")
    n = X.shape[0]
    if n == 0:
        raise ValueError(f"{name}X must contain at least one point")
    if not (Y.dim() == 1 or (Y.dim() == 2 and Y.shape[1] == 1)) or Y.shape[0] != n:
        raise ValueError(f"{name}Y must have shape ({n},) or ({n}, 1), got {tuple(Y.shape)}")
    Y = Y.detach().to(DTYPE).reshape(n, 1)
    if not torch.isfinite(Y).all():
        raise ValueError(f"{name}Y contains NaN or inf")
    return X.detach(), Y
