"""benchmarks/information_bound.py: the greedy oracle design and its replay on a known form."""

from __future__ import annotations

import itertools
import math
from types import SimpleNamespace

import pytest
import torch

from pigp_torch.models.inverse_sqrt import InverseSqrtPeakModel
from tests.benchmark.conftest import load_script
from tests.models.test_inverse_sqrt import DT, D, synthetic_prior, true_theta


@pytest.fixture(scope="module")
def bound():
    return load_script("information_bound")


@pytest.mark.parametrize("mu_scale", [0.3, 1.6])  # optimum inside the box, beyond a face
def test_greedy_design_regret_is_the_laplace_regret_of_the_chosen_readings(bound, mu_scale):
    """The Sherman-Morrison regrets fall monotonically and the last one equals
    0.5 beta g(x_hat)^-3/2 tr(M C_mu) of the Laplace covariance refitted on the chosen design."""
    prior = synthetic_prior()
    half = float(prior.bounds[1, 0])
    model = InverseSqrtPeakModel(prior, prior.bounds, residual_std=0.0)
    mu = torch.tensor([1.0, -0.5, 0.3, 0.2, -0.1], dtype=DT) * mu_scale * half
    model.theta = true_theta(model, mu, 0.8, 1.2)
    x_hat, active = model.box_optimum()
    assert bool(active.any()) == (mu_scale > 1)
    X = bound.candidates(model, x_hat, 256, seed=0)
    assert X.shape == (256 + 6 * 64, D)
    assert bool(((X >= prior.bounds[0]) & (X <= prior.bounds[1])).all())
    regrets, design = bound.greedy_design(model, X, 30, bar=0.0)
    assert len(regrets) == 31 and design.shape == (30, D)
    assert all(b <= a * (1 + 1e-12) for a, b in itertools.pairwise(regrets))
    assert regrets[-1] < 0.1 * regrets[0]
    model._laplace(design)
    scale = 0.5 * 1.2 * float(model.g(x_hat, model.theta)) ** -1.5
    expected = scale * float(torch.trace(model.regret_metric() @ model.cov[:D, :D]))
    assert regrets[-1] == pytest.approx(expected, rel=1e-8)
    # the design stops at the bar
    short, _ = bound.greedy_design(model, X, 30, bar=regrets[10])
    assert len(short) <= 12


def test_replay_on_the_form_itself_finds_the_optimum_within_the_predicted_regret(bound):
    """A machine that IS the form (noise 0.02): refits on the design land on its optimum, with
    a mean true regret of the order of the design's Laplace regret."""
    prior = synthetic_prior()
    half = float(prior.bounds[1, 0])
    model = InverseSqrtPeakModel(prior, prior.bounds, residual_std=0.0)
    mu = torch.tensor([0.3, -0.2, 0.1, 0.0, 0.2], dtype=DT) * half
    model.theta = true_theta(model, mu, 0.8, 1.0)
    theta = model.theta.clone()
    regrets, design = bound.greedy_design(model, bound.candidates(model, mu, 256, 1), 25, 0.0)
    machine = SimpleNamespace(loss_rate=lambda X: model.form(torch.atleast_2d(X), theta).squeeze())
    f_star = float(model.form(mu.unsqueeze(0), theta)[0])
    regret = bound.replay(model, machine, design, f_star, repeats=8, seed=0)
    assert torch.equal(model.theta, theta)  # restored
    assert bool((regret >= -1e-12).all())
    assert 0.1 * regrets[-1] < float(regret.mean()) < 3 * regrets[-1]
    assert math.isfinite(float(regret.max()))
