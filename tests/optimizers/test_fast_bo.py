"""Tests of FastBayesOpt: exact posterior vs BoTorch, incremental factor, derivatives, proposals."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from botorch.acquisition import (
    ExpectedImprovement,
    LogExpectedImprovement,
    UpperConfidenceBound,
)
from botorch.acquisition.analytic import _log_ei_helper
from gpytorch.means import LinearMean

from pigp_torch.bench.bo_speed import synthetic_problem
from pigp_torch.models import physics_informed_gp
from pigp_torch.optimizers import BayesOpt
from pigp_torch.optimizers.fast_bo import (
    MIN_NOISE_VARIANCE,
    FastBayesOpt,
    IncrementalGP,
    _log_h,
    maximize_in_unit_box,
)

D = torch.float64


def design(bounds, n, seed):
    g = torch.Generator().manual_seed(seed)
    return bounds[0] + (bounds[1] - bounds[0]) * torch.rand(
        n, bounds.shape[1], generator=g, dtype=D
    )


def told(opt, X, Y):
    for x, y in zip(X, Y, strict=True):
        opt.tell(x, float(y))
    return opt


def noisy_data(d=13, n=40, seed=0):
    prior, f, bounds = synthetic_problem(d, seed)
    X = prior.x0 + 0.3 * design(bounds, n, seed + 1)  # a cloud around the peak
    g = torch.Generator().manual_seed(seed + 2)
    Y = f(X) + 0.04 * torch.randn(n, generator=g, dtype=D)
    return prior, f, bounds, X, Y


def botorch_posterior(model, Xt):
    with torch.no_grad():
        post = model.posterior(Xt)
    return post.mean.squeeze(-1), post.variance.squeeze(-1)


def test_posterior_equals_physics_informed_gp():
    """Mean and variance equal BoTorch's PI-GP (kernel, f_inf mean, noise) to 1e-9 at 13 knobs."""
    prior, _, bounds, X, Y = noisy_data()
    opt = told(FastBayesOpt.from_prior(bounds, prior), X, Y)
    Xt = torch.cat([design(bounds, 100, 7), prior.x0 + 0.3 * design(bounds, 50, 8), X[:5] + 1e-5])
    mu, var = opt.posterior(Xt)
    mu_ref, var_ref = botorch_posterior(physics_informed_gp(X, Y, prior), Xt)
    assert torch.allclose(mu, mu_ref, atol=1e-9, rtol=0)
    assert torch.allclose(var, var_ref, atol=1e-9, rtol=0)
    # not a vacuous comparison: the data moved the mean, near the data the variance is small
    assert (mu - prior.f_inf).abs().max() > 0.1
    assert var[-5:].max() < 0.01 * prior.amplitude


def test_posterior_with_callable_mean_and_minimization():
    """A gpytorch Mean as prior mean, swapped by set_mean, and maximize=False all match BoTorch."""
    prior, _, bounds, X, Y = noisy_data(d=4, n=25)
    lin = LinearMean(4).to(D)
    lin.weights.data = torch.tensor([[3.0], [-2.0], [1.0], [0.5]], dtype=D)
    lin.bias.data.fill_(0.4)
    Xt = design(bounds, 30, 3)

    opt = told(FastBayesOpt.from_prior(bounds, prior, mean=lin), X, Y)
    mu_ref, var_ref = botorch_posterior(physics_informed_gp(X, Y, prior, mean=lin), Xt)
    mu, var = opt.posterior(Xt)
    assert torch.allclose(mu, mu_ref, atol=1e-9, rtol=0)
    assert torch.allclose(var, var_ref, atol=1e-9, rtol=0)

    opt.set_mean(0.7)  # alpha recomputed, factor kept
    mu_ref, _ = botorch_posterior(physics_informed_gp(X, Y, prior, mean=0.7), Xt)
    assert torch.allclose(opt.posterior(Xt)[0], mu_ref, atol=1e-9, rtol=0)

    # minimizing y is maximizing -y; the mean is given in y's units and negated internally
    mini = told(FastBayesOpt.from_prior(bounds, prior, mean=0.7, maximize=False), X, Y)
    model_neg = physics_informed_gp(X, -Y, prior, mean=-0.7)
    mu_neg, var_neg = botorch_posterior(model_neg, Xt)
    mu, var = mini.posterior(Xt)
    assert torch.allclose(mu, -mu_neg, atol=1e-9, rtol=0)
    assert torch.allclose(var, var_neg, atol=1e-9, rtol=0)


def test_incremental_factor_equals_fresh_one_after_many_tells():
    """After 300 tells (storage regrown 5x) C, A = G^-1 and alpha equal a fresh factorization."""
    prior, f, bounds = synthetic_problem(6, 3)
    X = design(bounds, 300, 5)
    Y = f(X)
    gp = IncrementalGP(prior.precision, prior.amplitude, prior.noise, mean=prior.f_inf)
    for x, y in zip(X, Y, strict=True):
        gp.add(x.numpy(), float(y))
    diff = X[:, None, :] - X[None, :, :]
    q = torch.einsum("ijk,kl,ijl->ij", diff, prior.precision, diff)
    G = prior.amplitude * torch.exp(-0.5 * q) + prior.noise**2 * torch.eye(300, dtype=D)
    C = torch.linalg.cholesky(G)
    assert np.abs(gp.cholesky - C.numpy()).max() < 1e-10
    A = torch.cholesky_inverse(C)
    assert np.abs(gp.inverse - A.numpy()).max() < 1e-8 * A.abs().max().item()
    alpha = A @ (Y - prior.f_inf)
    assert np.abs(gp.alpha - alpha.numpy()).max() < 1e-8 * alpha.abs().max().item()
    # posterior mean at the data, y - s^2 alpha, equals K alpha + m
    K = G - prior.noise**2 * torch.eye(300, dtype=D)
    assert np.allclose(gp.train_mean(), (prior.f_inf + K @ alpha).numpy(), atol=1e-9)


def test_noise_floor_matches_gpytorch():
    """Noise below GPyTorch's float64 floor (1e-6 variance) is rounded up as GPyTorch does."""
    prior, _, bounds, X, Y = noisy_data(d=3, n=10)
    prior.noise = 1e-5
    opt = told(FastBayesOpt.from_prior(bounds, prior), X, Y)
    assert opt.gp.noise_variance == MIN_NOISE_VARIANCE == 1e-6
    Xt = design(bounds, 10, 1)
    with pytest.warns(Warning, match="Very small noise"):
        model = physics_informed_gp(X, Y, prior)
    mu_ref, var_ref = botorch_posterior(model, Xt)
    mu, var = opt.posterior(Xt)
    assert torch.allclose(mu, mu_ref, atol=1e-8, rtol=0)
    assert torch.allclose(var, var_ref, atol=1e-9, rtol=0)


@pytest.mark.filterwarnings("ignore:ExpectedImprovement has known numerical issues")
@pytest.mark.parametrize("acquisition", ["ucb", "ei", "logei"])
def test_acquisition_and_gradient_equal_botorch_autograd(acquisition):
    """Values and closed-form gradients equal BoTorch's acquisition and its autograd gradient."""
    prior, _, bounds, X, Y = noisy_data(d=5, n=30)
    opt = told(FastBayesOpt.from_prior(bounds, prior, acquisition=acquisition, beta=2.5), X, Y)
    model = physics_informed_gp(X, Y, prior)
    ref = {
        "ucb": UpperConfidenceBound(model, beta=2.5),
        "ei": ExpectedImprovement(model, best_f=Y.max()),
        "logei": LogExpectedImprovement(model, best_f=Y.max()),
    }[acquisition]
    Xt = torch.cat([design(bounds, 8, 11), X[:2] + 2e-4])
    Xg = Xt.clone().requires_grad_(True)
    value_ref = ref(Xg[:, None, :])
    (grad_ref,) = torch.autograd.grad(value_ref.sum(), Xg)
    value, grad = opt.acquisition_value(Xt, order=1)
    assert torch.allclose(value, value_ref.detach(), atol=1e-9, rtol=1e-9)
    assert torch.allclose(grad, grad_ref, atol=1e-9 * grad_ref.abs().max().item(), rtol=1e-7)


@pytest.mark.parametrize("acquisition", ["ucb", "ei", "logei"])
def test_hessian_matches_finite_differences_of_gradient(acquisition):
    """The closed-form Hessian equals central differences of the gradient and is symmetric."""
    prior, _, bounds, X, Y = noisy_data(d=4, n=20)
    opt = told(FastBayesOpt.from_prior(bounds, prior, acquisition=acquisition), X, Y)
    Xt = torch.cat([design(bounds, 4, 2), X[:1] + 1e-4])
    _, grad, hess = opt.acquisition_value(Xt, order=2)
    h = 1e-7
    fd = torch.zeros_like(hess)
    for j in range(4):
        e = torch.zeros(4, dtype=D)
        e[j] = h
        fd[:, :, j] = (
            opt.acquisition_value(Xt + e, order=1)[1] - opt.acquisition_value(Xt - e, order=1)[1]
        ) / (2 * h)
    scale = hess.abs().amax(dim=(1, 2), keepdim=True)
    assert ((hess - fd).abs() / scale).max() < 1e-5
    assert torch.allclose(hess, hess.transpose(1, 2), atol=1e-12 * scale.max().item())
    assert (grad.abs().sum(1) > 0).all()


def test_log_h_matches_botorch_helper_far_into_the_tail():
    """log h(z) (the LogEI core) equals BoTorch's helper from z = -1e4 to 10; Phi/h is finite."""
    z = np.concatenate([-np.geomspace(1e4, 1e-3, 200), np.linspace(0, 10, 50)])
    log_h, ratio = _log_h(z)
    ref = _log_ei_helper(torch.tensor(z, dtype=D)).numpy()
    assert np.allclose(log_h, ref, rtol=1e-9, atol=1e-10)
    assert np.isfinite(ratio).all() and (ratio > 0).all()
    # d/dz log h = Phi / h: central differences in the well-conditioned range
    zz = np.linspace(-30, 5, 50)
    step = 1e-6
    fd = (_log_h(zz + step)[0] - _log_h(zz - step)[0]) / (2 * step)
    assert np.allclose(_log_h(zz)[1], fd, rtol=1e-6)


def test_newton_solver_finds_box_constrained_maximum():
    """Projected Newton: a concave quadratic's box maximum (clip of an outside peak) in few steps,
    a rotated quadratic's interior peak, and a convex start (|eigenvalue| ascent) both converge."""
    c = np.array([1.4, 0.3, -0.2, 0.6])
    Dg = np.array([1.0, 30.0, 5.0, 100.0])

    def quad(U, order):
        r = U - c
        v = -(Dg * r * r).sum(1)
        if order == 0:
            return v
        return v, -2 * Dg * r, np.broadcast_to(-2 * np.diag(Dg), (U.shape[0], 4, 4)).copy()

    U0 = np.array([[0.5, 0.5, 0.5, 0.5], [0.0, 1.0, 0.9, 0.1]])
    U, f, info = maximize_in_unit_box(quad, U0)
    assert np.allclose(U, np.clip(c, 0, 1)[None], atol=1e-9)
    assert info["iterations"] <= 5

    # interior peak of a rotated quadratic plus a bump (non-quadratic, convex at the start)
    g = np.random.default_rng(0)
    Q, _ = np.linalg.qr(g.standard_normal((3, 3)))
    M = Q @ np.diag([1.0, 10.0, 50.0]) @ Q.T
    c3 = np.array([0.4, 0.55, 0.6])

    def bump(U, order):
        r = U - c3
        e = np.exp(-0.5 * np.einsum("ki,ij,kj->k", r, M, r))
        if order == 0:
            return e
        Mr = r @ M
        hess = e[:, None, None] * (Mr[:, :, None] * Mr[:, None, :] - M)
        return e, -e[:, None] * Mr, hess

    U, f, _ = maximize_in_unit_box(bump, np.array([[0.0, 0.0, 0.0], [0.9, 0.1, 0.95]]))
    assert np.allclose(U, c3[None], atol=1e-7)
    assert np.allclose(f, 1.0, atol=1e-12)


def run_loop(opt, f, x0, steps, seed=0):
    g = torch.Generator().manual_seed(seed)
    x = x0
    history = []
    for _ in range(steps):
        y = float(f(x[None])[0]) + 0.04 * float(torch.randn((), generator=g, dtype=D))
        opt.tell(x, y)
        best_x = opt.best()[0]
        x = opt.ask()
        history.append((best_x, x, opt.last_info))
    return history


def test_proposals_stay_in_bounds_and_trust_box():
    """Every proposal lies in the bounds and within step_limit (normalized) of the best point,
    also when the best point sits at a bound (the box is cut by the bounds)."""
    prior, f, bounds = synthetic_problem(5, 1)
    opt = FastBayesOpt.from_prior(bounds, prior, step_limit=0.2)
    half = (bounds[1] - bounds[0]) / 2
    x0 = bounds[0].clone()  # a corner: the trust box is cut by the bounds
    hist = run_loop(opt, f, x0, 25)
    for best_x, x, info in hist:
        assert (x >= bounds[0]).all() and (x <= bounds[1]).all()
        assert ((x - best_x).abs() / half).max() <= 0.2 + 1e-12
        assert (x >= info["trust_lower"]).all() and (x <= info["trust_upper"]).all()
        assert torch.equal(info["center"], best_x)
    # the optimizer makes progress towards the peak (1.7) from the corner
    Y = torch.tensor(opt.Y)
    assert float(f(torch.stack(opt.X)).max()) > float(f(x0[None])[0]) + 0.3
    assert Y.numel() == 25


@pytest.mark.parametrize("d,method", [(13, "auto"), (4, "lbfgsb")])
def test_acquisition_value_at_least_optimize_acqf(d, method):
    """On the same data the proposal's UCB (BoTorch model) is >= optimize_acqf's (10 restarts,
    256 raw samples) within 1e-6, at several states of a run."""
    prior, f, bounds = synthetic_problem(d, 2)
    opt = FastBayesOpt.from_prior(bounds, prior, step_limit=0.3, method=method)
    hist = run_loop(opt, f, torch.zeros(d, dtype=D), 16, seed=1)
    assert hist[-1][2]["solver"] == ("newton" if method == "auto" else "lbfgsb")
    for n in (4, 16):
        X, Y = torch.stack(opt.X[:n]), torch.tensor(opt.Y[:n], dtype=D)
        fresh = told(FastBayesOpt.from_prior(bounds, prior, step_limit=0.3, method=method), X, Y)
        stock = told(
            BayesOpt(
                bounds,
                lambda X_, Y_: physics_informed_gp(X_, Y_, prior),
                step_limit=0.3,
                num_restarts=10,
                raw_samples=256,
            ),
            X,
            Y,
        )
        acq = UpperConfidenceBound(physics_informed_gp(X, Y, prior), beta=4.0)
        x_fast, x_stock = fresh.ask(), stock.ask()
        with torch.no_grad():
            v_fast, v_stock = acq(x_fast[None, None]).item(), acq(x_stock[None, None]).item()
        assert v_fast >= v_stock - 1e-6
        assert fresh.last_info["acq_value"] == pytest.approx(v_fast, abs=1e-12)
        # the same trust box as BayesOpt
        assert torch.equal(fresh.last_info["trust_lower"], stock.last_info["trust_lower"])


def test_deterministic_and_global_rng_untouched():
    """Same seed -> identical proposals; the global torch RNG state is not used."""
    prior, f, bounds = synthetic_problem(6, 4)
    runs = []
    for _ in range(2):
        opt = FastBayesOpt.from_prior(bounds, prior, seed=5, num_restarts=3, raw_samples=32)
        runs.append(torch.stack([h[1] for h in run_loop(opt, f, torch.zeros(6, dtype=D), 8)]))
        torch.manual_seed(123)  # perturbing the global RNG between runs changes nothing
    assert torch.equal(runs[0], runs[1])
    opt = FastBayesOpt.from_prior(bounds, prior, seed=5)
    opt.tell(torch.zeros(6, dtype=D), 1.0)
    before = torch.get_rng_state()
    opt.ask()
    assert torch.equal(before, torch.get_rng_state())


def test_minimize_mirrors_maximize():
    """Minimizing f proposes exactly what maximizing -f proposes."""
    prior, f, bounds = synthetic_problem(3, 5)
    a = FastBayesOpt.from_prior(bounds, prior, mean=0.3)
    b = FastBayesOpt.from_prior(bounds, prior, mean=-0.3, maximize=False)
    xa = xb = torch.zeros(3, dtype=D)
    for _ in range(6):
        a.tell(xa, float(f(xa[None])[0]))
        b.tell(xb, -float(f(xb[None])[0]))
        xa, xb = a.ask(), b.ask()
        assert torch.allclose(xa, xb, atol=1e-12)


def test_validation_errors():
    """Clear ValueErrors for bad options, shapes and solver/mean combinations."""
    prior, _, bounds = synthetic_problem(3, 0)
    with pytest.raises(ValueError, match="acquisition must be one of"):
        FastBayesOpt.from_prior(bounds, prior, acquisition="pi")
    with pytest.raises(ValueError, match="method='newton' needs a constant prior mean"):
        FastBayesOpt.from_prior(bounds, prior, mean=lambda X: X.sum(-1), method="newton")
    with pytest.raises(ValueError, match=r"unknown options \['maxcor'\] for method 'newton'"):
        FastBayesOpt.from_prior(bounds, prior, method="newton", options={"maxcor": 5})
    with pytest.raises(ValueError, match="precision is 3 x 3, bounds have 2"):
        FastBayesOpt(bounds[:, :2], prior.precision, amplitude=1.0, noise=0.1)
    with pytest.raises(ValueError, match="amplitude must be positive"):
        FastBayesOpt(bounds, prior.precision, amplitude=0.0, noise=0.1)
    with pytest.raises(ValueError, match='mean must be "f_inf", "zero"'):
        FastBayesOpt.from_prior(bounds, prior, mean="median")
    with pytest.raises(ValueError, match="need num_restarts >= 0 and raw_samples >= num_restarts"):
        FastBayesOpt.from_prior(bounds, prior, num_restarts=5, raw_samples=2)
    with pytest.raises(RuntimeError, match="tell\\(\\) the start point first"):
        FastBayesOpt.from_prior(bounds, prior).ask()
    bad_mean = FastBayesOpt.from_prior(bounds, prior, mean=lambda X: X)  # N x d, not N
    with pytest.raises(ValueError, match="mean must return one value per row"):
        bad_mean.tell(torch.zeros(3, dtype=D), 1.0)
    assert bad_mean.n_told == 0 and bad_mean.gp.n == 0  # history and GP stay consistent
