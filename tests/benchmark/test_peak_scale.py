"""benchmarks/peak_scale.py: a machine's peak against the prior's expectation."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from tests.benchmark.conftest import load_script

DT = torch.float64


@pytest.fixture(scope="module")
def scale():
    return load_script("peak_scale")


def test_generalized_eigenvalues_are_those_of_the_whitened_matrix(scale):
    """The eigenvalues of A v = lambda B v equal those of L^-1 A L^-T (B = L L^T), and a
    multiple k B of B has k as its only eigenvalue."""
    g = torch.Generator().manual_seed(3)
    R = torch.randn(6, 6, generator=g, dtype=DT)
    B = R @ R.T + 6 * torch.eye(6, dtype=DT)
    S = torch.randn(6, 6, generator=g, dtype=DT)
    A = S @ S.T + 0.1 * torch.eye(6, dtype=DT)
    L = torch.linalg.cholesky(B)
    W = torch.linalg.solve_triangular(L, torch.linalg.solve_triangular(L, A, upper=False).T,
                                      upper=False)  # fmt: skip
    ref = torch.linalg.eigvalsh((W + W.T) / 2)
    torch.testing.assert_close(scale.generalized_eigenvalues(A, B), ref)
    lam = scale.generalized_eigenvalues(2.5 * B, B)
    torch.testing.assert_close(lam, torch.full((6,), 2.5, dtype=DT))


@pytest.mark.slow
def test_a_machine_against_its_own_peak_is_one_everywhere(scale):
    """With a prior made of the machine's own peak (shape, height, background), every ratio
    of the row is 1 and log beta 0."""
    from pigp_torch.bench.machines import benchmark_ring
    from pigp_torch.bench.oracle import machine_peak
    from pigp_torch.prior import PhysicsPrior
    from pigp_torch.simulation.spec import SPEAR3

    prior = PhysicsPrior.load(scale.PRIOR)
    sim = benchmark_ring(103, SPEAR3, True)
    mu, B = machine_peak(sim)
    f_inf = float(sim.loss_background)
    own = dataclasses.replace(prior, f_inf=f_inf, f_x0=float(sim.loss_rate(mu)), peak_shape=B)
    row = scale.machine_row(own, 103, "project")
    for key in ("beta_min", "beta_med", "beta_max", "c_ratio", "width"):
        assert row[key] == pytest.approx(1.0, rel=1e-9), key
    assert row["log_beta"] == pytest.approx(0.0, abs=1e-8)
    assert row["f_inf"] == row["f_inf_prior"] == f_inf
