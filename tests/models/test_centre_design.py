"""The correlated centre information and its average over the form's posterior, against a
brute-force recomputation of the Laplace covariance with one more reading."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pigp_torch.models._centre_design import design_states, expected_information
from pigp_torch.models.inverse_sqrt import InverseSqrtPeakModel
from tests.contracts.parts import DT, HALF, make_prior, readings

PRIOR = make_prior()
X, Y = readings(PRIOR, n=9)


def _fitted(**options) -> InverseSqrtPeakModel:
    model = InverseSqrtPeakModel(PRIOR, PRIOR.bounds, **options)
    model.fit(X, Y)
    return model


def _points(n: int = 6, spread: float = 0.8) -> torch.Tensor:
    g = torch.Generator().manual_seed(5)
    return (torch.rand(n, X.shape[1], generator=g, dtype=DT) * 2 - 1) * HALF * spread


def _brute(model: InverseSqrtPeakModel, x: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    r""":math:`\mathrm{tr}(B C_\mu) - \mathrm{tr}(B C'_\mu)` at ``theta``, :math:`C` and
    :math:`C'` inverted from :math:`J^\top\Sigma^{-1}J + \Lambda_0` of the told readings and of
    the told ones plus ``x`` (``d``), :math:`\Sigma` the residual GP's covariance of the readings
    (differentiable in ``x``)."""
    d, told = model.dim, model._X
    prior = model.prior_precision()
    B = model.shape(theta)

    def trace(Xs: torch.Tensor) -> torch.Tensor:
        J = model.jacobian(Xs, theta)
        if model.residual_std > 0:
            S = model._k_res(Xs, Xs) + model.noise**2 * torch.eye(len(Xs), dtype=DT)
        else:
            S = model.noise**2 * torch.eye(len(Xs), dtype=DT)
        C = torch.linalg.inv(J.T @ torch.linalg.solve(S, J) + prior)
        return torch.trace(B @ C[:d, :d])

    return trace(told) - trace(torch.cat([told, x[None]]))


@pytest.mark.parametrize("options", [{}, {"gls": True}, {"f_inf_std": 0.05, "shape_std": 0.5}])
def test_correlated_update_equals_the_brute_force(options):
    """Values (rtol 1e-9) and closed-form gradients (autograd of the brute force) of the exact
    correlated update at six settings, for the fixed form, the GLS fit and a fitted shape."""
    model = _fitted(**options)
    xs = _points()
    info, grad = expected_information(model, xs.numpy())
    for i, x in enumerate(xs):
        x = x.clone().requires_grad_(True)
        ref = _brute(model, x, model.theta)
        (g,) = torch.autograd.grad(ref, x)
        np.testing.assert_allclose(info[i], float(ref.detach()), rtol=1e-9)
        np.testing.assert_allclose(grad[i], g.numpy(), rtol=1e-6, atol=1e-9 * g.abs().max().item())
    assert (info > 0).all()


def test_without_residual_gp_it_is_the_independent_information():
    """With ``residual_std = 0`` (:math:`\\mathbf k = 0`, :math:`\\Sigma = \\sigma_n^2 I`) the
    correlated update is the independent one, value and gradient (rtol 1e-10)."""
    model = _fitted(residual_std=0.0)
    xs = _points().numpy()
    info, grad = expected_information(model, xs)
    ref, ref_grad = model.centre_information_numpy(xs)
    np.testing.assert_allclose(info, ref, rtol=1e-10)
    np.testing.assert_allclose(grad, ref_grad, rtol=1e-8, atol=1e-12 * np.abs(ref_grad).max())


@pytest.mark.parametrize("rank", [1, 3])
def test_expected_information_averages_the_brute_force_over_sigma_points(rank):
    """The average over the sigma points equals the weighted brute force at their
    :math:`\\theta` (rtol 1e-9); its gradient matches central differences; the weights sum to
    one, the points' mean is :math:`\\hat\\theta`, and for ``rank = d`` their centres' spread is
    the Laplace covariance of the centre."""
    model = _fitted()
    states = design_states(model, rank)
    assert len(states) == 2 * rank + 1
    w = np.array([s["w"] for s in states])
    thetas = torch.stack([s["theta"] for s in states]).numpy()
    np.testing.assert_allclose(w.sum(), 1.0, rtol=1e-12)
    np.testing.assert_allclose(w @ thetas, model.theta.numpy(), rtol=1e-10, atol=1e-14)
    centre = states[0]["C"][: model.dim, : model.dim]
    dev = thetas[:, : model.dim] - model.theta.numpy()[: model.dim]
    spread = (w[:, None] * dev).T @ dev
    if rank == model.dim:
        np.testing.assert_allclose(spread, centre, rtol=1e-8, atol=1e-12 * np.abs(centre).max())
    xs = _points(4)
    info, grad = expected_information(model, xs.numpy(), rank)
    for i, x in enumerate(xs):
        ref = sum(s["w"] * float(_brute(model, x, s["theta"])) for s in states)
        np.testing.assert_allclose(info[i], ref, rtol=1e-9)
    h = 1e-7
    for k in range(model.dim):
        e = np.zeros(model.dim)
        e[k] = h
        up, _ = expected_information(model, xs.numpy() + e, rank)
        down, _ = expected_information(model, xs.numpy() - e, rank)
        np.testing.assert_allclose(grad[:, k], (up - down) / (2 * h), rtol=1e-5)
    point, _ = expected_information(model, xs.numpy(), 0)
    assert not np.allclose(info, point, rtol=1e-3)  # the average is not the point estimate


def test_design_states_refuse_bad_options_and_are_cached_per_fit():
    model = _fitted()
    with pytest.raises(ValueError, match="rank must be >= 0"):
        design_states(model, -1)
    with pytest.raises(ValueError, match="kappa > 0"):
        design_states(model, 2, 0.0)
    assert design_states(model, 2) is design_states(model, 2)
    first = design_states(model, 2)
    model.fit(X[:8], Y[:8])
    assert design_states(model, 2) is not first


@pytest.mark.parametrize("schedule", ["c", "e"])
def test_information_asks_keep_the_trust_box_and_the_travel_limit(schedule):
    """``pigp-physics`` with every ask of the letter ``c`` or ``e``: each proposal is an
    information ask, inside the trust box and within ``travel_limit`` of the last told point."""
    from pigp_torch.optimizers.physics_bo import PhysicsModelBO

    opt = PhysicsModelBO(PRIOR.bounds, PRIOR, schedule=schedule, travel_limit=0.2, n_starts=4)
    limit = 0.2 * HALF
    for x, y in zip(X[:4], Y[:4], strict=True):
        opt.tell(x, float(y))
    g = torch.Generator().manual_seed(2)
    for _ in range(4):
        x = opt.ask()
        info = opt.last_info
        assert info["inform"]
        assert (x >= info["trust_lower"] - 1e-12).all() and (x <= info["trust_upper"] + 1e-12).all()
        assert (torch.abs(x - opt.X[-1]) <= limit * (1 + 1e-9)).all()
        q = ((x - 0.002) @ PRIOR.precision * (x - 0.002)).sum()
        opt.tell(x, float(0.35 + 0.55 / torch.sqrt(1 + q) + 0.02 * torch.randn(1, generator=g)))
