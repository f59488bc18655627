"""Closed-form Gaussian objectives shared by the prior tests."""

from dataclasses import dataclass

import pytest
import torch

HALF_RANGE = 0.015  # knob half-range (K1sL in 1/m), as in the 13-knob benchmark


def random_spd(d: int, cond: float, lam_min: float, seed: int) -> torch.Tensor:
    """Random d x d SPD matrix, eigenvalues log-spaced in [lam_min, cond * lam_min]."""
    g = torch.Generator().manual_seed(seed)
    Q, _ = torch.linalg.qr(torch.randn(d, d, generator=g, dtype=torch.float64))
    eig = lam_min * torch.logspace(0.0, float(torch.log10(torch.tensor(cond))), d).double()
    P = Q @ torch.diag(eig) @ Q.T
    return 0.5 * (P + P.T)


@dataclass
class GaussianBump:
    """f(x) = f_inf + A exp(-1/2 (x - mu)^T P (x - mu)) on the box +-HALF_RANGE."""

    mu: torch.Tensor
    P: torch.Tensor
    A: float
    f_inf: float
    bounds: torch.Tensor

    def __call__(self, X: torch.Tensor) -> torch.Tensor:
        D = X - self.mu
        q = ((D @ self.P) * D).sum(-1)
        return self.f_inf + self.A * torch.exp(-0.5 * q)


def make_bump(d: int, seed: int = 0) -> GaussianBump:
    """Bump with correlation lengths 0.005 ... 0.05 (condition number 100), mu inside the box."""
    g = torch.Generator().manual_seed(100 + seed)
    P = random_spd(d, cond=100.0, lam_min=1 / 0.05**2, seed=seed)
    mu = 0.5 * HALF_RANGE * (2 * torch.rand(d, generator=g, dtype=torch.float64) - 1)
    bounds = torch.tensor([[-HALF_RANGE] * d, [HALF_RANGE] * d], dtype=torch.float64)
    return GaussianBump(mu=mu, P=P, A=1.5, f_inf=0.2, bounds=bounds)


@pytest.fixture(params=[4, 13], ids=["d4", "d13"])
def bump(request):
    return make_bump(request.param, seed=request.param)
