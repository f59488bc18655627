"""benchmarks/fit_diagnosis.py: the departure of a machine from the physics form."""

from __future__ import annotations

import pytest
import torch

from tests.benchmark.conftest import load_script

DT = torch.float64


@pytest.fixture(scope="module")
def diagnosis():
    return load_script("fit_diagnosis")


@pytest.mark.parametrize("gamma", [0.0, 0.03, -0.01])
def test_quadratic_departure_is_one_plus_gamma_q_for_a_quartic_g(diagnosis, gamma):
    """For f = f_inf + g^-1/2 with g = c + q + gamma q^2 (q in the metric of B) the ratio
    (g - c)/q along any unit direction is 1 + gamma q: 1 everywhere for the exact form."""
    g = torch.Generator().manual_seed(5)
    R = torch.randn(4, 4, generator=g, dtype=DT)
    B = R @ R.T + torch.eye(4, dtype=DT)
    mu = torch.tensor([0.3, -0.1, 0.2, 0.0], dtype=DT)
    c, f_inf = 0.8, 0.1

    def loss_rate(x):
        q = (x - mu) @ B @ (x - mu)
        return f_inf + (c + q + gamma * q**2) ** -0.5

    qs = (0.25, 1.0, 4.0, 9.0)
    ratio = diagnosis.quadratic_departure(loss_rate, f_inf, mu, B, qs, n_dirs=3)
    expected = torch.tensor([[1 + gamma * q for q in qs]] * 3, dtype=DT)
    torch.testing.assert_close(torch.from_numpy(ratio), expected, rtol=1e-9, atol=1e-9)
