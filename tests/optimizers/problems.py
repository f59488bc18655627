"""Test problems shared by the optimizer tests: a correlated quadratic, a driver, a box."""

from __future__ import annotations

import numpy as np
import torch

DT = torch.float64


def correlated_quadratic(d: int, seed: int, condition: float = 20.0):
    """Negative quadratic -(x-c)^T A (x-c) with a random rotation, eigenvalues 1..condition."""
    g = np.random.default_rng(seed)
    Q, _ = np.linalg.qr(g.standard_normal((d, d)))
    A = torch.tensor(Q @ np.diag(np.geomspace(1.0, condition, d)) @ Q.T)
    c = torch.tensor(g.uniform(-0.6, 0.6, d))
    return (lambda x: float(-(x - c) @ A @ (x - c))), c


def drive(opt, f, x0, budget: int, sigma: float = 0.0, seed: int = 0) -> list[float]:
    """Run ``budget`` evaluations (start included) with noise; return the noise-free values."""
    g = torch.Generator().manual_seed(seed)

    def measure(x):
        return f(x) + sigma * float(torch.randn((), generator=g, dtype=DT))

    opt.tell(x0, measure(x0))
    values = [f(x0)]
    for _ in range(budget - 1):
        x = opt.ask()
        opt.tell(x, measure(x))
        values.append(f(x))
    return values


def box(d: int, half: float = 1.0) -> torch.Tensor:
    return torch.tensor([[-half] * d, [half] * d], dtype=DT)
