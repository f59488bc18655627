"""The learned memory of the physics form: weighted fit, tau from the data, step detection."""

import math

import numpy as np
import pytest
import torch

from pigp_torch.models.forgetting import Forgetting
from pigp_torch.models.inverse_sqrt import InverseSqrtPeakModel, _NumpyObjective
from pigp_torch.optimizers.physics_bo import PhysicsModelBO
from tests.models.test_inverse_sqrt import F_INF, D, synthetic_prior, true_theta

DT = torch.float64


@pytest.fixture
def prior():
    return synthetic_prior()


def _readings(model, theta, n, seed, spread=0.01, noise=0.02):
    g = torch.Generator().manual_seed(seed)
    X = theta[:D] + (torch.rand(n, D, generator=g, dtype=DT) * 2 - 1) * spread
    return X, model.form(X, theta) + noise * torch.randn(n, generator=g, dtype=DT)


def test_weighted_fit_is_the_fit_with_noise_variance_sigma2_over_w(prior):
    """Weights w_i make reading i's variance noise² / w_i: the objective (torch and NumPy with
    its gradient), the Laplace precision J' W J / noise² + prior and the residual GP's mean and
    variance (K + diag(noise² / w)) all equal their written-out forms; w = 1 is the plain fit."""
    model = InverseSqrtPeakModel(prior, prior.bounds, residual_std=0.05)
    theta = true_theta(model, [0.003, -0.002, 0.001, 0.0, 0.002], 0.7, 1.2)
    X, Y = _readings(model, theta, 24, seed=3)
    w = torch.exp(-torch.arange(23, -1, -1, dtype=DT) / 8.0)
    model.fit(X, Y, weights=w)
    plain = InverseSqrtPeakModel(prior, prior.bounds, residual_std=0.05)
    plain.fit(X, Y)
    pen = float(plain._neg_log_post(theta, X, Y)) - 0.5 * float(
        ((Y - plain.form(X, theta)) / plain.noise).square().sum()
    )
    r = Y - model.form(X, theta)
    data = 0.5 * float((w * r**2).sum()) / model.noise**2
    assert float(model._neg_log_post(theta, X, Y)) == pytest.approx(data + pen, rel=1e-12)
    value, grad = _NumpyObjective(model, X, Y)(theta.numpy())
    th = theta.clone().requires_grad_(True)
    ref = model._neg_log_post(th, X, Y)
    ref.backward()
    assert value == pytest.approx(float(ref.detach()), rel=1e-12)
    np.testing.assert_allclose(grad, th.grad.numpy(), rtol=1e-8, atol=1e-10)
    J = model.jacobian(X)
    A = J.T @ torch.diag(w) @ J / model.noise**2 + model.prior_precision()
    torch.testing.assert_close(model.cov, torch.linalg.inv(A), rtol=1e-9, atol=0)
    Xs = X[:3] + 0.002
    K = model._k_res(X, X) + torch.diag(model.noise**2 / w)
    Ks = model._k_res(Xs, X)
    r = Y - model.form(X)
    Js = model.jacobian(Xs)
    mean = model.form(Xs) + Ks @ torch.linalg.solve(K, r)
    var = ((Js @ model.cov) * Js).sum(-1) + model.residual_std**2
    var = var - (Ks * torch.linalg.solve(K, Ks.T).T).sum(-1)
    mu, sd = model.predict(Xs)
    torch.testing.assert_close(mu, mean, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(sd, var.sqrt(), rtol=1e-8, atol=1e-12)
    ones = InverseSqrtPeakModel(prior, prior.bounds, residual_std=0.05)
    ones.fit(X, Y, weights=torch.ones(24, dtype=DT))
    torch.testing.assert_close(ones.theta, plain.theta, rtol=1e-7, atol=1e-9)
    assert ones.log_evidence() == pytest.approx(plain.log_evidence(), rel=1e-9)


def test_weights_drop_readings_below_the_floor_and_keep_the_origin():
    memory = Forgetting(floor=1e-2)
    assert memory.weights(100) == (0, None)  # tau = inf: every reading, unweighted
    first, w = memory.weights(100, tau=10.0)
    assert first == 100 - 1 - math.floor(10 * math.log(100))  # exp(-age / 10) >= 1e-2
    torch.testing.assert_close(w, torch.exp(-torch.arange(99 - first, -1, -1, dtype=DT) / 10))
    memory.origin = 95
    assert memory.weights(100, tau=10.0)[0] == 95 and memory.weights(100)[0] == 95


def _memory_after(prior, shift_per_reading: float, n: int = 100, seed: int = 0) -> Forgetting:
    """Readings scattered around a centre moving by ``shift_per_reading`` (half-range units of
    knob 0) each reading; the memory checked every 10 readings from 60 on."""
    model = InverseSqrtPeakModel(prior, prior.bounds)
    theta = true_theta(model, [0.002, -0.001, 0.0, 0.001, 0.0], 0.7, 1.0)
    g = torch.Generator().manual_seed(seed)
    X = torch.empty(n, D, dtype=DT)
    Y = torch.empty(n, dtype=DT)
    for t in range(n):
        th = theta.clone()
        th[0] += shift_per_reading * 0.015 * t
        X[t] = th[:D] + (torch.rand(D, generator=g, dtype=DT) * 2 - 1) * 0.006
        Y[t] = model.form(X[t : t + 1], th)[0] + prior.noise * torch.randn((), generator=g)
    memory = Forgetting()
    for m in range(60, n + 1, 10):
        memory.select(model, X[:m], Y[:m])
    return memory


def test_learned_tau_is_infinite_on_a_static_machine_and_short_on_a_drifting_one(prior):
    """The predictive-likelihood choice: a static machine keeps every reading (tau = inf); a
    centre moving by 0.01 half-ranges a reading (half a half-range over the run) is followed
    with a memory of at most 100 readings."""
    static = _memory_after(prior, 0.0)
    assert static.tau == math.inf
    drifting = _memory_after(prior, 0.01)
    assert drifting.tau <= 100.0
    lead = drifting.scores[drifting.tau, 0.0] - drifting.scores[math.inf, 0.0]
    assert lead > drifting.margin


def _decaying_memory(prior, slope: float, slopes, n: int = 90, seed: int = 0) -> Forgetting:
    """Readings scattered around a fixed centre whose height above the background falls as
    exp(slope * t); the memory (``slopes`` compared) checked every 10 readings from 60 on."""
    model = InverseSqrtPeakModel(prior, prior.bounds)
    theta = true_theta(model, [0.002, -0.001, 0.0, 0.001, 0.0], 0.7, 1.0)
    X, Y = _readings(model, theta, n, seed, spread=0.006, noise=prior.noise)
    Y = F_INF + (Y - F_INF) * torch.exp(slope * torch.arange(n, dtype=DT))
    memory = Forgetting(slopes=slopes)
    for m in range(60, n + 1, 10):
        memory.select(model, X[:m], Y[:m])
    return memory


def test_a_falling_height_is_tracked_by_its_slope_and_a_static_one_is_not(prior):
    """The part above the background brought to the latest reading is b + (y - b) e^{s age};
    a height falling by 1 % per reading (the peak halves in 70 readings) is followed by the
    slope of the grid nearest to it, a static one keeps (tau, s) = (inf, 0)."""
    memory = Forgetting(slopes=(0.0, -0.01))
    Y = torch.tensor([1.0, 2.0, 3.0], dtype=DT)
    expected = 0.5 + (Y - 0.5) * torch.exp(-0.01 * torch.tensor([2.0, 1.0, 0.0], dtype=DT))
    torch.testing.assert_close(memory.rescale(Y, 0.5, -0.01), expected, rtol=1e-15, atol=0)
    assert memory.rescale(Y, 0.5) is Y  # slope 0 (the default): the readings themselves
    grid = (0.0, -0.003, -0.01)
    assert _decaying_memory(prior, -0.01, grid).slope == -0.01
    static = _decaying_memory(prior, 0.0, grid)
    assert (static.tau, static.slope) == (math.inf, 0.0)
    with pytest.raises(ValueError, match="slopes must start with 0"):
        Forgetting(slopes=(-0.01, 0.0))


def test_a_step_is_detected_within_ten_readings_and_not_on_a_static_machine(prior):
    """The CUSUM of the innovations: 150 readings of a static machine raise no alarm; after the
    centre jumps by 0.3 half-ranges the alarm comes within 10 readings, restarts the memory at
    the excursion and makes a notice."""
    model = InverseSqrtPeakModel(prior, prior.bounds)
    theta = true_theta(model, [0.002, -0.001, 0.0, 0.001, 0.0], 0.7, 1.0)
    X, Y = _readings(model, theta, 150, seed=5, spread=0.004)
    memory = Forgetting()
    model.fit(X[:60], Y[:60])
    alarms = [memory.observe(model, X[t], float(Y[t])) for t in range(150)]
    assert not any(alarms)
    moved = theta.clone()
    moved[0] += 0.3 * 0.015
    Xs, Ys = _readings(model, theta, 10, seed=6, spread=0.004)  # near the old optimum
    Ys = model.form(Xs, moved) + prior.noise * torch.randn(10, generator=torch.Generator())
    hits = [memory.observe(model, Xs[t], float(Ys[t])) for t in range(10)]
    assert any(hits)
    at = hits.index(True)
    assert memory.origin >= 150 - 1 and memory.origin <= 150 + at
    (notice,) = memory.notices
    assert notice["kind"] == "drift_step" and notice["n"] == 151 + at


def _drifting_run(prior, forgetting, n=160, seed=1, shift=0.2):
    """PhysicsModelBO on a machine whose centre moves ``shift`` half-ranges along knob 0 over
    ``n`` readings (more than the peak's width there); returns the gain (f_t(x_t) - f_t(0)) /
    (f_t* - f_t(0)) against the moving optimum per reading, and the optimizer."""
    model = InverseSqrtPeakModel(prior, prior.bounds)
    theta = true_theta(model, [0.003, -0.002, 0.001, 0.0, 0.002], 0.6, 1.0)
    bo = PhysicsModelBO(prior.bounds, prior, seed=seed, n_starts=2, forgetting=forgetting)
    g = torch.Generator().manual_seed(seed)
    x, gains = torch.zeros(D, dtype=DT), []
    for t in range(n):
        th = theta.clone()
        th[0] -= shift * 0.015 * t / n
        f0, fx = (float(model.form(v.unsqueeze(0), th)[0]) for v in (torch.zeros(D, dtype=DT), x))
        gains.append((fx - f0) / (F_INF + math.exp(-0.5 * float(th[D])) - f0))
        bo.tell(x, fx + prior.noise * float(torch.randn((), generator=g, dtype=DT)))
        x = bo.ask()
    return np.array(gains), bo


@pytest.mark.slow
def test_a_drifting_machine_is_followed_where_the_fixed_memory_loses_it(prior):
    """Over the last 60 of 160 readings the default (learned memory) keeps >= 0.65 of the
    moving gain on average (measured 0.77); the same method without forgetting (every reading
    for good, the method before the memory) falls to <= 0.35 (measured 0.13). ``recommend`` is
    the fitted optimum and ``tracked`` reports the unknowns with units."""
    follow, bo = _drifting_run(prior, True)
    fixed, _ = _drifting_run(prior, False)
    assert follow[100:].mean() >= 0.65
    assert fixed[100:].mean() <= 0.35
    assert bo.parts.posterior.drifting and bo.parts.posterior.forgetting.tau < math.inf
    tracked = bo.tracked()
    assert tracked["peak"][1] == "mA/min" and tracked["centre_moved"][1] == "A"
    assert tracked["remembered"][0] < 100 and tracked["centre_moved"][0] > 0
    torch.testing.assert_close(bo.recommend(), bo.model.box_optimum()[0])


def test_the_misfit_test_counts_the_remembered_readings(prior):
    """With a memory of 10 readings the fit remembers sum(w) ~ 10.5 < p + 5 = 12 readings: the
    prior check's misfit test (chi2 on nu = sum(w) - p) does not run, where on all 80 readings
    (no forgetting) the same far-off readings reject the prior."""
    from pigp_torch.models.physics_posterior import PhysicsFormPosterior

    model = InverseSqrtPeakModel(prior, prior.bounds)
    theta = true_theta(model, [0.002, -0.001, 0.0, 0.001, 0.0], 0.7, 1.0)
    X, Y = _readings(model, theta, 80, seed=2)
    Y = Y + 0.3 * torch.sin(X[:, 0] / 0.002)  # a ripple the form cannot fit
    kept, plain = (
        PhysicsFormPosterior(prior, prior.bounds, forgetting=f, evidence_from=1000)  # misfit only
        for f in ({"start": 1000}, False)  # no check of tau: it stays at the one set here
    )
    kept.forgetting.tau = 10.0
    kept.fit(X, Y)
    plain.fit(X, Y)
    assert float(kept.model.weights.sum()) < kept.model.n_params + 5
    assert kept.misfit_z is None and kept.stage == 0
    assert plain.misfit_z > plain.check_z and plain.stage == len(plain.relax)
