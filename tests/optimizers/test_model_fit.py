"""The online-fitted model optimizer: the regularized least-squares fit and the ask/tell loop."""

from __future__ import annotations

import pytest
import torch

from pigp_torch.optimizers.model_fit import FittedModelOptimizer, fit_unknowns

D = torch.float64


def _linear_model(X: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    """o = (theta_0 x_0 + theta_1, theta_2 x_1): linear in the unknowns."""
    return torch.stack([theta[..., 0] * X[:, 0] + theta[..., 1], theta[..., 2] * X[:, 1]], -1)


def test_fit_matches_closed_form_for_a_linear_model():
    """For a model linear in the unknowns the Levenberg-Marquardt fit is the closed-form
    regularized least-squares solution u = (J'J/s^2 + I/sd^2)^-1 J'(o - m0)/s^2."""
    gen = torch.Generator().manual_seed(0)
    X = torch.rand(7, 2, generator=gen, dtype=D)
    c = torch.tensor([1.0, -0.5, 2.0], dtype=D)
    h = torch.tensor([0.5, 0.2, 1.0], dtype=D)
    O = _linear_model(X, torch.tensor([1.3, -0.4, 1.2], dtype=D))
    O = O + 0.01 * torch.randn(O.shape, generator=gen, dtype=D)
    s, sd = 0.01, 0.6
    u, cost = fit_unknowns(_linear_model, X, O, c, h, obs_sd=s, prior_sd=sd)
    J = torch.autograd.functional.jacobian(
        lambda v: _linear_model(X, c + h * v).reshape(-1), torch.zeros(3, dtype=D)
    )
    m0 = _linear_model(X, c).reshape(-1)
    A = J.T @ J / s**2 + torch.eye(3, dtype=D) / sd**2
    u_exact = torch.linalg.solve(A, J.T @ (O.reshape(-1) - m0) / s**2)
    torch.testing.assert_close(u, u_exact, rtol=1e-8, atol=1e-10)
    r = torch.cat([((O - _linear_model(X, c + h * u)) / s).reshape(-1), u / sd])
    assert cost == pytest.approx(float(r @ r), rel=1e-10)


def test_optimizer_finds_target_of_known_model_family():
    """With a model family that contains the machine, the optimizer drives the observables to a
    reachable target within a few readings, stays in the bounds, and needs the observables."""
    truth = torch.tensor([1.4, -0.3, 0.8], dtype=D)
    target = torch.tensor([0.5, -0.4], dtype=D)
    bounds = torch.tensor([[-1.0, -1.0], [1.0, 1.0]], dtype=D)
    opt = FittedModelOptimizer(
        bounds,
        model=_linear_model,
        goal=lambda o: ((o - target).square() + 1e-12).sqrt().mean(-1),
        theta_center=torch.tensor([1.0, 0.0, 1.0], dtype=D),
        theta_half_width=torch.tensor([0.5, 0.5, 0.5], dtype=D),
        obs_sd=1e-6,
        trust=1.0,
        maximize=False,
    )
    x = torch.zeros(2, dtype=D)
    errs = []
    for _ in range(6):
        o = _linear_model(x[None], truth)[0]
        err = float((o - target).abs().mean())
        errs.append(err)
        opt.tell(x, err, observables=o)
        x = opt.ask()
        assert ((x >= bounds[0]) & (x <= bounds[1])).all()
    assert errs[0] > 0.1 and min(errs) < 1e-4
    with pytest.raises(ValueError, match="observables"):
        opt.tell(x, 0.0)
