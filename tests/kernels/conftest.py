"""Shared fixtures for kernel tests: random SPD precision matrices."""

import pytest
import torch


def random_spd(d: int, cond: float = 100.0, seed: int = 0) -> torch.Tensor:
    """Random d x d SPD matrix with eigenvalues log-spaced in [1, cond]."""
    g = torch.Generator().manual_seed(seed)
    Q, _ = torch.linalg.qr(torch.randn(d, d, generator=g, dtype=torch.float64))
    eig = torch.logspace(0, torch.log10(torch.tensor(cond)).item(), d, dtype=torch.float64)
    P = Q @ torch.diag(eig) @ Q.T
    return 0.5 * (P + P.T)


@pytest.fixture
def spd():
    return random_spd
