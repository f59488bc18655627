"""Optima over an error ensemble of model rings, and their covariance (the centre prior)."""

import pytest
import torch

from pigp_torch.simulation import Spear3Coupling
from pigp_torch.simulation.ensemble import (
    ENSEMBLE_SEED0,
    center_covariance,
    ensemble_seeds,
    machine_centers,
)


def test_ensemble_seeds_are_consecutive_from_1001():
    assert ensemble_seeds(3) == [ENSEMBLE_SEED0, ENSEMBLE_SEED0 + 1, ENSEMBLE_SEED0 + 2] == [
        1001, 1002, 1003
    ]  # fmt: skip
    with pytest.raises(ValueError, match="at least one ring"):
        ensemble_seeds(0)


def test_machine_centers_are_unconstrained_maxima():
    """Each row is a stationary point of the ring's loss rate (gradient ~0, inside the 4x box),
    at least as high as the ring's optimum within the knob box and above skews-off."""
    seeds, X = machine_centers([1001, 1002], progress=False)
    assert seeds == [1001, 1002] and X.shape == (2, 13) and X.dtype == torch.float64
    for s, x in zip(seeds, X, strict=True):
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


def test_center_covariance_closed_form_and_singular_ensemble():
    X = torch.tensor([[1.0, 0.0], [0.0, 2.0], [1.0, 2.0]], dtype=torch.float64)
    expected = torch.tensor([[2.0, 2.0], [2.0, 8.0]], dtype=torch.float64) / 3
    assert torch.allclose(center_covariance(X), expected, rtol=0, atol=1e-15)
    with pytest.raises(ValueError, match="singular"):
        center_covariance(X[:1])


def test_machine_centers_input_checks():
    with pytest.raises(ValueError, match="no seeds"):
        machine_centers([])
    with pytest.raises(ValueError, match="reach"):
        machine_centers([1001], reach=0.5)
