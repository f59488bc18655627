"""Optima over an error ensemble of model rings, their covariance (the centre prior) and the mean
shape of the peak."""

import pytest
import torch

from pigp_torch.prior.hessian import log_excess_hessian
from pigp_torch.simulation import Spear3Coupling
from pigp_torch.simulation.ensemble import (
    ENSEMBLE_SEED0,
    EnsembleOptima,
    center_covariance,
    ensemble_optima,
    ensemble_seeds,
    mean_shape,
    peak_shape_at,
)


def test_ensemble_seeds_are_consecutive_from_1001():
    assert ensemble_seeds(3) == [ENSEMBLE_SEED0, ENSEMBLE_SEED0 + 1, ENSEMBLE_SEED0 + 2] == [
        1001, 1002, 1003
    ]  # fmt: skip
    with pytest.raises(ValueError, match="at least one ring"):
        ensemble_seeds(0)


def test_ensemble_optima_are_unconstrained_maxima_with_their_shapes():
    """Each centre is a stationary point of the ring's loss rate (gradient ~0, inside the 4x
    box), at least as high as the ring's optimum within the knob box and above skews-off; the
    shape there is the log-Hessian's -H / (f - f_inf)^2 (the two agree at a stationary point)."""
    optima = ensemble_optima([1001, 1002], progress=False)
    seeds, X = optima.seeds, optima.centers
    assert seeds == [1001, 1002] and X.shape == (2, 13) and X.dtype == torch.float64
    assert optima.shapes.shape == (2, 13, 13) and optima.seed_range == [1001, 1002, 2]
    for s, x, B in zip(seeds, X, optima.shapes, strict=True):
        sim = Spear3Coupling(s)
        assert (x.abs() < 4 * sim.knob_limit * (1 - 1e-6)).all()
        xg = x.clone().requires_grad_(True)
        f = sim.loss_rate(xg)
        (grad,) = torch.autograd.grad(f, xg)
        # gradient in units of the knob half-range: ~0 against an O(1) drop over the box
        assert float((grad * sim.knob_limit).abs().max()) < 1e-3
        f_box = sim.loss_rate(sim.optimum(n_starts=2)[0])
        f = f.detach()
        assert float(f) >= float(f_box) - 1e-9
        assert float(f) > float(sim.loss_rate(torch.zeros(13, dtype=torch.float64)))
        H, _, f_x = log_excess_hessian(sim.loss_rate, x, sim.loss_background)
        torch.testing.assert_close(B, -H / (f_x - sim.loss_background) ** 2, rtol=1e-4, atol=0)
        assert float(torch.linalg.eigvalsh(B).min()) > 0


def test_center_covariance_closed_form_and_singular_ensemble():
    X = torch.tensor([[1.0, 0.0], [0.0, 2.0], [1.0, 2.0]], dtype=torch.float64)
    expected = torch.tensor([[2.0, 2.0], [2.0, 8.0]], dtype=torch.float64) / 3
    assert torch.allclose(center_covariance(X), expected, rtol=0, atol=1e-15)
    with pytest.raises(ValueError, match="singular"):
        center_covariance(X[:1])


def test_ensemble_optima_input_checks():
    with pytest.raises(ValueError, match="no seeds"):
        ensemble_optima([])
    with pytest.raises(ValueError, match="reach"):
        ensemble_optima([1001], reach=0.5)


class _Quadratic:
    """A stand-in ring whose (f - f_inf)^-2 is exactly c + (x - mu)' B (x - mu)."""

    loss_background = 0.35

    def __init__(self, B, mu, c):
        self.B, self.mu, self.c = B, mu, c

    def loss_rate(self, X):
        Z = X - self.mu
        return self.loss_background + (self.c + ((Z @ self.B) * Z).sum(-1)) ** -0.5


def test_peak_shape_is_exact_for_a_quadratic_g_anywhere():
    """g = (f - f_inf)^-2 quadratic => half its Hessian is B at every point, not only at mu."""
    g = torch.Generator().manual_seed(0)
    A = torch.randn(4, 4, generator=g, dtype=torch.float64)
    B = A @ A.T + torch.eye(4, dtype=torch.float64)
    ring = _Quadratic(B, torch.tensor([0.1, -0.2, 0.0, 0.3], dtype=torch.float64), 0.8)
    for x in (ring.mu, torch.tensor([0.3, 0.1, -0.2, 0.0], dtype=torch.float64)):
        torch.testing.assert_close(peak_shape_at(ring, x), B, rtol=1e-10, atol=1e-12)


def test_mean_shape_and_prior_fields_closed_form():
    B1 = torch.tensor([[2.0, 1.0], [1.0, 2.0]], dtype=torch.float64)
    B2 = torch.tensor([[4.0, 0.0], [0.0, 1.0]], dtype=torch.float64)
    expected = torch.tensor([[3.0, 0.5], [0.5, 1.5]], dtype=torch.float64)
    assert torch.equal(mean_shape(torch.stack([B1, B2])), expected)
    X = torch.tensor([[1.0, 0.0], [0.0, 2.0]], dtype=torch.float64)
    fields = EnsembleOptima([7, 9], X, torch.stack([B1, B2])).prior_fields()
    assert set(fields) == {"center_cov", "peak_shape"}
    assert torch.equal(fields["peak_shape"], expected)
    assert torch.equal(
        fields["center_cov"], torch.diag(torch.tensor([0.5, 2.0], dtype=torch.float64))
    )
    with pytest.raises(ValueError, match="n x d x d"):
        mean_shape(B1)
