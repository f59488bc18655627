"""Tests of the BayesOpt ask/tell optimizer (trust box, acquisition conventions, determinism)."""

from __future__ import annotations

import functools
import math

import pytest
import torch
from botorch.models import SingleTaskGP
from gpytorch.kernels import RBFKernel, ScaleKernel
from gpytorch.means import ConstantMean
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pigp_torch.optimizers.bayesopt import BayesOpt

D = torch.float64


def fixed_gp(X, Y, *, lengthscale, outputscale=0.1, noise=1e-4, mean=0.0):
    """A GP with a fixed ARD-RBF kernel, constant mean and fixed noise (nothing is fitted)."""
    kernel = ScaleKernel(RBFKernel(ard_num_dims=X.shape[-1])).to(D)
    kernel.base_kernel.lengthscale = torch.as_tensor(lengthscale, dtype=D)
    kernel.outputscale = outputscale
    mean_module = ConstantMean().to(D)
    mean_module.constant.data.fill_(mean)
    model = SingleTaskGP(
        X,
        Y,
        train_Yvar=torch.full_like(Y, noise),
        covar_module=kernel,
        mean_module=mean_module,
        outcome_transform=None,
    )
    return model.eval()


X_STAR = torch.tensor([0.5, -0.4], dtype=D)
WIDTH = torch.tensor([0.3, 0.5], dtype=D)
BOUNDS_2D = torch.tensor([[-1.0, -1.0], [1.0, 1.0]], dtype=D)


def peak(x):
    """Heavy-tailed peak 1/sqrt(1 + |(x - x*)/w|^2), maximum 1 at x*."""
    z = (torch.as_tensor(x, dtype=D) - X_STAR) / WIDTH
    return float(1.0 / torch.sqrt(1.0 + (z**2).sum()))


def run_bo(budget=20, noise=0.01, **kwargs):
    """Run BO from the origin with seeded noise; return the noise-free values of all evaluations."""
    gen = torch.Generator().manual_seed(1)
    factory = functools.partial(fixed_gp, lengthscale=[0.3, 0.5], mean=0.3)
    kw = {"step_limit": 0.25, "num_restarts": 4, "raw_samples": 64, **kwargs}
    bo = BayesOpt(BOUNDS_2D, factory, **kw)
    x = torch.zeros(2, dtype=D)
    values = []
    for i in range(budget):
        values.append(peak(x))
        bo.tell(x, values[-1] + noise * float(torch.randn((), generator=gen, dtype=D)))
        if i < budget - 1:
            x = bo.ask()
    return values, bo


def test_bo_improves_and_beats_random_search():
    """In 20 evaluations BO climbs from 0.476 to >= 0.99 (peak 1); random search stays < 0.95."""
    values, _ = run_bo()
    assert values[0] == pytest.approx(0.4757, abs=1e-3)
    assert max(values) >= 0.99
    gen = torch.Generator().manual_seed(1)
    lo, hi = BOUNDS_2D
    random_points = lo + torch.rand(19, 2, generator=gen, dtype=D) * (hi - lo)
    random_best = max([values[0]] + [peak(r) for r in random_points])
    assert random_best < 0.95
    assert max(values) - random_best > 0.04


def test_steps_respect_step_limit_along_the_run():
    """Each proposal lies within step_limit (normalized) of the best point told before it."""
    _, bo = run_bo(budget=12, step_limit=0.2)
    X = torch.stack(bo.X)
    Y = torch.tensor(bo.Y, dtype=D)
    for k in range(1, len(X)):
        best = X[int(Y[:k].argmax())]
        assert (X[k] - best).abs().max() <= 0.2 * 1.0 + 1e-12


@pytest.mark.filterwarnings("ignore::botorch.exceptions.warnings.NumericsWarning")
@settings(
    max_examples=12, deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow]
)
@given(
    d=st.integers(1, 3),
    n=st.integers(1, 6),
    data_seed=st.integers(0, 10_000),
    step_limit=st.one_of(st.none(), st.floats(0.01, 2.5)),
    center=st.sampled_from(["best_observed", "best_mean"]),
    acquisition=st.sampled_from(["ucb", "ei", "logei"]),
    outside=st.booleans(),
)
def test_proposals_stay_in_bounds_and_trust_box(
    d, n, data_seed, step_limit, center, acquisition, outside
):
    """Whatever the data, step limit, center rule or acquisition, ask() stays in bounds and box."""
    gen = torch.Generator().manual_seed(data_seed)
    lower = -torch.rand(d, generator=gen, dtype=D) * 0.02 - 1e-3
    upper = torch.rand(d, generator=gen, dtype=D) * 0.02 + 1e-3
    bounds = torch.stack([lower, upper])
    X = lower + torch.rand(n, d, generator=gen, dtype=D) * (upper - lower)
    if outside:  # a point told from outside the bounds (archive data) must not empty the box
        X[0] = upper + 0.01
    Y = torch.randn(n, generator=gen, dtype=D)
    factory = functools.partial(fixed_gp, lengthscale=(upper - lower).tolist(), noise=1e-2)
    bo = BayesOpt(
        bounds,
        factory,
        step_limit=step_limit,
        trust_center=center,
        acquisition=acquisition,
        num_restarts=2,
        raw_samples=16,
        seed=data_seed,
    )
    for xi, yi in zip(X, Y, strict=True):
        bo.tell(xi, float(yi))
    x = bo.ask()
    assert x.shape == (d,) and x.dtype == D
    assert (x >= lower).all() and (x <= upper).all()
    info = bo.last_info
    c = info["center"]
    assert any(torch.equal(c, xi) for xi in X)
    if center == "best_observed":
        assert torch.equal(c, X[int(Y.argmax())])
    assert (x >= info["trust_lower"]).all() and (x <= info["trust_upper"]).all()
    if step_limit is not None:
        c_in = torch.minimum(torch.maximum(c, lower), upper)
        assert ((x - c_in).abs() <= step_limit * (upper - lower) / 2 * (1 + 1e-12)).all()


def test_best_mean_center_ignores_a_lucky_outlier():
    """A single planted high reading is the best_observed center but not the best_mean one."""
    xs = torch.linspace(-1, 1, 21, dtype=D).unsqueeze(-1)
    ys = 1.0 - (xs.squeeze(-1) - 0.3) ** 2  # smooth, peak at x = 0.3
    i_out = 3  # x = -0.7, true value 0.0
    ys[i_out] = 1.5  # lucky reading, above the true peak
    factory = functools.partial(fixed_gp, lengthscale=[0.3], outputscale=1.0, noise=0.05**2)
    centers = {}
    for rule in ("best_observed", "best_mean"):
        bo = BayesOpt([[-1.0], [1.0]], factory, trust_center=rule, num_restarts=2, raw_samples=16)
        for xi, yi in zip(xs, ys, strict=True):
            bo.tell(xi, float(yi))
        bo.ask()
        centers[rule] = float(bo.last_info["center"])
    assert centers["best_observed"] == pytest.approx(-0.7)
    assert centers["best_mean"] == pytest.approx(0.3)


def _posterior(bo, x):
    with torch.no_grad():
        post = bo.last_model.posterior(x.unsqueeze(0))
    return float(post.mean), float(post.variance.sqrt())


@pytest.mark.parametrize("beta", [4.0, 9.0])
def test_ucb_uses_sqrt_beta(beta):
    """UCB at the proposal is mu + sqrt(beta) sigma (beta = 4 gives the authors' mu + 2 sigma)."""
    _, bo = run_bo(budget=4, beta=beta)
    x = bo.ask()
    mu, sigma = _posterior(bo, x)
    assert sigma > 1e-3  # so that mu + beta sigma would differ measurably
    assert bo.last_info["acq_value"] == pytest.approx(mu + math.sqrt(beta) * sigma, rel=1e-9)
    assert abs(bo.last_info["acq_value"] - (mu + beta * sigma)) > 1e-3


@pytest.mark.filterwarnings("ignore::botorch.exceptions.warnings.NumericsWarning")
@pytest.mark.parametrize("acquisition", ["ei", "logei"])
def test_expected_improvement_closed_form(acquisition):
    """EI at the proposal is (mu - y*) Phi(z) + sigma phi(z), y* the best observed reading."""
    _, bo = run_bo(budget=4, acquisition=acquisition, step_limit=None)
    x = bo.ask()
    mu, sigma = _posterior(bo, x)
    z = (mu - max(bo.Y)) / sigma
    normal = torch.distributions.Normal(0.0, 1.0)
    ei = (mu - max(bo.Y)) * float(normal.cdf(torch.tensor(z))) + sigma * math.exp(
        -0.5 * z * z
    ) / math.sqrt(2 * math.pi)
    expected = ei if acquisition == "ei" else math.log(ei)
    assert bo.last_info["acq_value"] == pytest.approx(expected, rel=1e-6)


def test_minimize_negates_targets_and_picks_lowest_reading_as_center():
    """maximize=False hands -y to the model factory and centers the box on the lowest reading."""
    seen = {}

    def factory(X, Y):
        seen["Y"] = Y.clone()
        return fixed_gp(X, Y, lengthscale=[0.5, 0.5])

    bo = BayesOpt(BOUNDS_2D, factory, maximize=False, num_restarts=2, raw_samples=16)
    pts = torch.tensor([[0.0, 0.0], [0.5, 0.5], [-0.5, 0.2]], dtype=D)
    for p, y in zip(pts, [3.0, 1.0, 2.0], strict=True):
        bo.tell(p, y)
    bo.ask()
    assert torch.equal(seen["Y"].squeeze(-1), torch.tensor([-3.0, -1.0, -2.0], dtype=D))
    assert torch.equal(bo.last_info["center"], pts[1])
    assert bo.best()[1] == 1.0


@pytest.mark.filterwarnings("ignore::botorch.exceptions.warnings.NumericsWarning")
def test_asks_are_deterministic_and_leave_the_global_rng_alone():
    """Same seed -> identical proposals; the global torch RNG state is not changed by ask()."""
    state = torch.get_rng_state()
    _, bo1 = run_bo(budget=5, noise=0.0)
    assert torch.equal(torch.get_rng_state(), state)
    _, bo2 = run_bo(budget=5, noise=0.0)
    assert all(torch.equal(a, b) for a, b in zip(bo1.X, bo2.X, strict=True))
    _, bo3 = run_bo(budget=5, noise=0.0, seed=7, step_limit=None, acquisition="ei")
    assert not all(torch.equal(a, b) for a, b in zip(bo1.X, bo3.X, strict=True))


def test_trust_box_formula_and_whole_box_without_limit():
    """Box = clamp(center, bounds) +- step_limit (h - l)/2, cut to the bounds; None = bounds."""
    bounds = torch.tensor([[-0.015, 0.0], [0.015, 1.0]], dtype=D)
    factory = functools.partial(fixed_gp, lengthscale=[0.01, 0.5])
    bo = BayesOpt(bounds, factory, step_limit=0.1)
    box = bo.trust_box(torch.tensor([0.0149, 0.5], dtype=D))
    expected = torch.tensor([[0.0134, 0.45], [0.015, 0.55]], dtype=D)
    assert torch.allclose(box, expected, atol=1e-15)
    box = bo.trust_box(torch.tensor([0.02, 0.5], dtype=D))  # center outside: clamped to 0.015
    assert float(box[0, 0]) == pytest.approx(0.0135)
    assert torch.equal(BayesOpt(bounds, factory, step_limit=None).trust_box(box[0]), bounds)


def test_info_and_told_points_that_were_never_asked():
    """tell() accepts points never asked; last_info reports timings and the training size."""
    _, bo = run_bo(budget=3)
    bo.tell(torch.tensor([0.9, 0.9], dtype=D), 0.1)  # archive point
    bo.ask()
    info = bo.last_info
    assert info["n_train"] == 4
    assert info["fit_time_s"] >= 0.0 and info["acq_time_s"] > 0.0
    assert info["trust_upper"].shape == (2,)


def test_bad_arguments_raise():
    """Bad options raise ValueError; asking before any tell raises RuntimeError."""
    factory = functools.partial(fixed_gp, lengthscale=[0.5, 0.5])
    with pytest.raises(ValueError, match="acquisition"):
        BayesOpt(BOUNDS_2D, factory, acquisition="pi")
    with pytest.raises(ValueError, match="step_limit"):
        BayesOpt(BOUNDS_2D, factory, step_limit=0.0)
    with pytest.raises(ValueError, match="trust_center"):
        BayesOpt(BOUNDS_2D, factory, trust_center="middle")
    with pytest.raises(ValueError, match="beta"):
        BayesOpt(BOUNDS_2D, factory, beta=-1.0)
    with pytest.raises(ValueError, match="raw_samples"):
        BayesOpt(BOUNDS_2D, factory, num_restarts=8, raw_samples=4)
    with pytest.raises(ValueError, match="callable"):
        BayesOpt(BOUNDS_2D, "gp")
    with pytest.raises(RuntimeError, match="tell"):
        BayesOpt(BOUNDS_2D, factory).ask()
    bo = BayesOpt(BOUNDS_2D, lambda X, Y: "not a model")
    bo.tell(torch.zeros(2, dtype=D), 1.0)
    with pytest.raises(ValueError, match="not a Model"):
        bo.ask()
