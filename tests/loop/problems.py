"""The 2-knob test problem of the loop tests: a bowl with its top at x* = (0.3, -0.2)."""

import torch

D = torch.float64
BOUNDS = torch.tensor([[-1.0, -1.0], [1.0, 1.0]], dtype=D)
X_STAR = torch.tensor([0.3, -0.2], dtype=D)


def bowl(x) -> float:
    """1 - |x - x*|^2, maximum 1 at x* = (0.3, -0.2)."""
    return float(1.0 - ((torch.as_tensor(x, dtype=D) - X_STAR) ** 2).sum())
