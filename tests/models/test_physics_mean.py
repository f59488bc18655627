"""Tests of the physics-structured prior mean and its MAP fit."""

import math

import pytest
import torch

from pigp_torch.models import PhysicsMean, fit_physics_mean, physics_informed_gp
from pigp_torch.prior import PhysicsPrior

D = 3
F_INF = 0.35


def _precision():
    g = torch.Generator().manual_seed(0)
    A = torch.randn(D, D, generator=g, dtype=torch.float64)
    return (A @ A.T + D * torch.eye(D, dtype=torch.float64)) * 1e4


def _prior():
    return PhysicsPrior(
        x0=torch.tensor([0.001, -0.002, 0.0], dtype=torch.float64),
        f_x0=1.2,
        f_inf=F_INF,
        precision=_precision(),
        amplitude=0.02,
        noise=0.01,
        knob_names=["a", "b", "c"],
        bounds=torch.tensor([[-0.015] * D, [0.015] * D], dtype=torch.float64),
    )


def test_mean_closed_form():
    """forward equals f_inf + A / sqrt(1 + 2 s (x - mu)^T P (x - mu)) for batched inputs."""
    P = _precision()
    mu = torch.tensor([0.001, 0.002, -0.001], dtype=torch.float64)
    m = PhysicsMean(P, F_INF, mu, peak=1.3, scale=2.0)
    X = 0.004 * torch.randn(
        2, 5, D, dtype=torch.float64, generator=torch.Generator().manual_seed(1)
    )
    d = X - mu
    q = torch.einsum("...i,ij,...j->...", d, P, d)
    expected = F_INF + 1.3 / torch.sqrt(1 + 4.0 * q)
    with torch.no_grad():
        got = m(X)
    assert got.shape == (2, 5)
    torch.testing.assert_close(got, expected, rtol=1e-12, atol=1e-12)
    with torch.no_grad():
        assert float(m(mu.unsqueeze(0))[0]) == pytest.approx(F_INF + 1.3, rel=1e-12)


def test_eigen_scales_scale_each_direction():
    """A log eigen-scale a_1 multiplies the curvature along the top eigenvector by exp(a_1) only."""
    P = _precision()
    m = PhysicsMean(P, F_INF, torch.zeros(D, dtype=torch.float64), peak=1.0, n_eigen_scales=1)
    with torch.no_grad():
        m.log_eigen_scales.fill_(math.log(3.0))
        v_top, v_low = m.eigenvectors[:, 0], m.eigenvectors[:, -1]
        q_top = m.quadratic((1e-3 * v_top).unsqueeze(0))[0]
        q_low = m.quadratic((1e-3 * v_low).unsqueeze(0))[0]
    assert float(q_top) == pytest.approx(2 * 3.0 * float(m.eigenvalues[0]) * 1e-6, rel=1e-10)
    assert float(q_low) == pytest.approx(2 * float(m.eigenvalues[-1]) * 1e-6, rel=1e-10)


def test_hessian_of_log_excess_matches_prior():
    """With s = 1 the Hessian of log(m - f_inf) at mu is -2 P (the model ring's Hessian)."""
    P = _precision()
    mu = torch.tensor([0.001, 0.0, -0.002], dtype=torch.float64)
    m = PhysicsMean(P, F_INF, mu, peak=0.8)
    H = torch.autograd.functional.hessian(
        lambda x: torch.log(m(x.unsqueeze(0))[0] - F_INF), mu.clone()
    )
    torch.testing.assert_close(H, -2 * P, rtol=1e-8, atol=1e-6)


def test_fit_recovers_parameters():
    """The MAP fit on noise-free data of a known mean recovers its centre, peak and scale."""
    P = _precision()
    truth = PhysicsMean(P, F_INF, torch.tensor([0.002, -0.001, 0.001]), peak=1.4, scale=3.0)
    g = torch.Generator().manual_seed(2)
    X = 0.004 * torch.randn(40, D, generator=g, dtype=torch.float64)
    with torch.no_grad():
        Y = truth(X)
    m = PhysicsMean(P, F_INF, torch.zeros(D, dtype=torch.float64), peak=1.0)
    loss = fit_physics_mean(
        m,
        X,
        Y,
        1e-6 * torch.eye(40, dtype=torch.float64),
        center_prior=torch.zeros(D, dtype=torch.float64),
        center_std=torch.tensor(0.01),
        peak_prior=1.0,
        log_std=3.0,
        max_iter=200,
    )
    torch.testing.assert_close(m.center.detach(), truth.center.detach(), rtol=0, atol=2e-5)
    assert float(m.log_peak.exp()) == pytest.approx(1.4, rel=1e-3)
    assert float(m.log_scale.exp()) == pytest.approx(3.0, rel=1e-2)
    assert loss < 1.0
    assert not m.center.requires_grad


def test_fit_rejects_bad_shapes():
    """Mismatched X / covariance sizes and NaN readings raise ValueError."""
    m = PhysicsMean(_precision(), F_INF, torch.zeros(D), peak=1.0)
    X = torch.zeros(4, D, dtype=torch.float64)
    Y = torch.ones(4, dtype=torch.float64)
    kw = dict(center_prior=torch.zeros(D), center_std=torch.tensor(0.01), peak_prior=1.0)
    with pytest.raises(ValueError, match="covariance"):
        fit_physics_mean(m, X, Y, torch.eye(3, dtype=torch.float64), **kw)
    with pytest.raises(ValueError, match="X must be"):
        fit_physics_mean(m, X[:, :2], Y, torch.eye(4, dtype=torch.float64), **kw)
    with pytest.raises(ValueError, match="finite"):
        fit_physics_mean(m, X, Y * float("nan"), torch.eye(4, dtype=torch.float64), **kw)


def test_constructor_validation():
    """Non-positive peak, wrong centre size and too many eigen scales raise ValueError."""
    P = _precision()
    with pytest.raises(ValueError, match="peak"):
        PhysicsMean(P, F_INF, torch.zeros(D), peak=0.0)
    with pytest.raises(ValueError, match="center"):
        PhysicsMean(P, F_INF, torch.zeros(D + 1), peak=1.0)
    with pytest.raises(ValueError, match="n_eigen_scales"):
        PhysicsMean(P, F_INF, torch.zeros(D), peak=1.0, n_eigen_scales=D + 1)


def test_from_prior_and_gp_posterior_mean():
    """from_prior uses A = f(x0) - f_inf, and the PI-GP with it has the closed-form posterior."""
    prior = _prior()
    m = PhysicsMean.from_prior(prior)
    assert float(m.log_peak.detach().exp()) == pytest.approx(1.2 - F_INF, rel=1e-12)
    torch.testing.assert_close(m.center.detach(), prior.x0)
    g = torch.Generator().manual_seed(3)
    X = 0.005 * torch.randn(6, D, generator=g, dtype=torch.float64)
    Y = 0.5 + torch.rand(6, generator=g, dtype=torch.float64)
    Xs = 0.005 * torch.randn(4, D, generator=g, dtype=torch.float64)
    model = physics_informed_gp(X, Y, prior, mean=m)

    def k(A, B):
        Dl = A[:, None, :] - B[None, :, :]
        return prior.amplitude * torch.exp(
            -0.5 * torch.einsum("nmi,ij,nmj->nm", Dl, prior.precision, Dl)
        )

    with torch.no_grad():
        K = k(X, X) + prior.noise**2 * torch.eye(6, dtype=torch.float64)
        expected = m(Xs) + k(Xs, X) @ torch.linalg.solve(K, Y - m(X))
        got = model.posterior(Xs).mean.reshape(-1)
    torch.testing.assert_close(got, expected, rtol=1e-8, atol=1e-10)
