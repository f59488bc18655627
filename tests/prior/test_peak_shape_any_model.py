"""The physics form's peak shape and the ensemble of optima come from any machine model, by one
code path (:mod:`pigp_torch.prior.peak_shape`, :func:`~pigp_torch.prior.machine_model.
machine_peak_shape`, :func:`~pigp_torch.prior.machine_model.machine_optima`): the ring's model
gives what the ring's own error ensemble gives, and ARES-EA's model gives the Hessian of its
:math:`(f - f_\\infty)^{-2}`."""

from __future__ import annotations

import pytest
import torch

from pigp_torch._utils import DTYPE
from pigp_torch.machines import KINDS
from pigp_torch.prior.machine_model import (
    machine_optima,
    machine_peak_shape,
    prior_from_machine_model,
)
from pigp_torch.prior.peak_shape import mean_shape


@pytest.fixture(scope="module")
def ring():
    sim = KINDS["spear3"].simulator(error_seed=0)
    return sim, KINDS["spear3"].model(sim=sim)


@pytest.fixture(scope="module")
def ares():
    """ARES-EA's model for trial 0's target (goal: the smoothed MAE in µm), at the published
    start setting, with the background the prior would take (the largest goal sampled)."""
    from pigp_torch.machines.ares_ea.prior import ares_model_um
    from pigp_torch.machines.ares_ea.simulation import START_SETTING, load_trials
    from pigp_torch.prior.machine_model import _largest_goal

    model = ares_model_um(load_trials()[0].target)
    g_inf = _largest_goal(model, model.unknown_center, seed=0, n_samples=64)
    return model, torch.tensor(START_SETTING, dtype=DTYPE), g_inf


def test_the_rings_model_gives_the_rings_own_peak_shape_to_the_bit(ring):
    """At the centre of its unknowns the ring's machine model is the model ring, so its peak
    shape is the error ensemble's (``ensemble.peak_shape_at``), bit for bit."""
    from pigp_torch.machines.ring.ensemble import peak_shape_at

    sim, model = ring
    x = 0.2 * sim.bounds[1] * torch.linspace(-1, 1, sim.dim, dtype=DTYPE)
    B = machine_peak_shape(model, x)
    assert B.shape == (sim.dim, sim.dim)
    assert torch.equal(B, peak_shape_at(sim, x))


def test_the_rings_ensemble_of_optima_moves_with_its_unknowns(ring):
    """Draw k of the unknowns (coupling errors δ, map background d and scale e) is the model ring
    at x + δ with its excess over the background scaled by 1 + e: its shape is the ring's at
    x + δ over (1 + e)², and its optimum is where the ring's gradient vanishes."""
    from pigp_torch.machines.ring.ensemble import _g_derivatives, peak_shape_at

    sim, model = ring
    K = sim.dim
    optima = machine_optima(model, 2, seed=3, n_starts=1, shapes=True)
    assert optima.centers.shape == (2, K) and optima.shapes.shape == (2, K, K)
    for theta, x, B in zip(optima.thetas, optima.centers, optima.shapes, strict=True):
        delta, e = theta[:K], float(theta[K + 1])
        expected = peak_shape_at(sim, x + delta) / (1 + e) ** 2
        assert float((B - expected).abs().max()) <= 1e-9 * float(expected.abs().max())
        inside = (x.abs() < 0.999 * sim.bounds[1]).all()
        if inside:  # a maximum inside the box: g = (f - f_inf)^-2 is stationary there
            _, G = _g_derivatives(sim, x + delta)
            newton = torch.linalg.solve(B, G / (1 + e) ** 2) / 2  # knob units
            assert float((newton.abs() / sim.bounds[1]).max()) < 1e-3
        assert bool((torch.linalg.eigvalsh(B) > 0).all())


def _g(model, X, g_inf):
    """:math:`(f - f_\\infty)^{-2}` of the model's objective ``f = -goal``, written out."""
    return (g_inf - model.goal_at(X, model.unknown_center)) ** -2


def test_ares_peak_shape_is_the_curvature_of_its_excess(ares):
    """ARES-EA's shape through the same code: :math:`B` gives the second differences of
    :math:`g = (g_\\infty - \\mathrm{goal})^{-2}` along each knob and along a mixed direction
    (central differences, step 1e-6 of each knob's range: the smoothed MAE bends on a scale of
    1e-4 of the correctors' range; agreement within 5e-3 relative, the rounding of the flattest
    directions)."""
    model, x, g_inf = ares
    B = machine_peak_shape(model, x, goal_background=g_inf)
    assert B.shape == (5, 5) and torch.allclose(B, B.T)
    h = 1e-6 * (model.bounds[1] - model.bounds[0])
    directions = [*torch.eye(5, dtype=DTYPE), torch.ones(5, dtype=DTYPE)]
    with torch.no_grad():
        for u in directions:
            step = u * h
            X = torch.stack([x + step, x - step, x])
            gp, gm, g0 = _g(model, X, g_inf)
            second = float((gp + gm - 2 * g0) / 2)  # = step^T B step + O(h^4)
            predicted = float(step @ B @ step)
            assert second == pytest.approx(predicted, rel=5e-3)


def test_a_model_without_a_background_needs_one(ares):
    model, x, _ = ares
    assert model.goal_background is None
    with pytest.raises(ValueError, match="has no goal_background: give one"):
        machine_peak_shape(model, x)


def test_the_prior_carries_the_ensembles_mean_shape_when_asked(ring):
    """``prior_from_machine_model(..., n_ensemble, peak_shape=True)``: the prior's
    ``peak_shape`` is the mean of :func:`machine_optima`'s shapes and its ``center_cov`` the
    same draws' covariance; without ``peak_shape`` the prior has none (as before)."""
    _, model = ring
    small = {"n_starts": 1, "n_samples": 64, "seed": 5}
    prior = prior_from_machine_model(model, noise=0.04, n_ensemble=2, peak_shape=True, **small)
    optima = machine_optima(model, 2, seed=5, n_starts=1, shapes=True)
    assert torch.equal(prior.peak_shape, mean_shape(optima.shapes))
    assert prior.provenance["ensemble_mean"] == optima.centers.mean(0).tolist()
    plain = prior_from_machine_model(model, noise=0.04, **small)
    assert plain.peak_shape is None and torch.equal(plain.x0, prior.x0)


@pytest.mark.slow
def test_ares_prior_gets_the_ensembles_shape_through_the_same_path(ares):
    """ARES-EA's prior with the physics form's shape: positive definite, the mean of the shapes
    at the draws' optima (slow: two optimum searches of the Cheetah model)."""
    model, _, _ = ares
    small = {"n_starts": 2, "n_samples": 64, "seed": 0}
    prior = prior_from_machine_model(model, noise=1.0, n_ensemble=2, peak_shape=True, **small)
    assert prior.peak_shape.shape == (5, 5)
    assert bool((torch.linalg.eigvalsh(prior.peak_shape) > 0).all())
