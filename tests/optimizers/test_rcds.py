"""Tests for the ask/tell RCDS optimizer and its noise-robust line search."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from pigp_torch.optimizers.rcds import (
    RCDS,
    fit_parabola_minimum,
    line_minimize,
    powell_keeps_directions,
)

from .problems import DT, box, correlated_quadratic, drive


def run_coroutine(coroutine, f):
    """Answer every point a coroutine yields with f(u); return (its return value, the points)."""
    points = []
    try:
        u = next(coroutine)
        while True:
            points.append(u)
            u = coroutine.send(f(u))
    except StopIteration as stop:
        return stop.value, points


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_noisy_quadratic_5d_gain_fraction(seed):
    """On a correlated 5-D quadratic (condition 20) with noise 3 % of the gain (told to RCDS), 300
    evaluations reach >= 97 % of the possible noise-free gain."""
    f, _ = correlated_quadratic(5, seed)
    x0 = torch.zeros(5, dtype=DT)
    gain = 0.0 - f(x0)
    sigma = 0.03 * gain
    values = drive(RCDS(box(5), noise=sigma), f, x0, 300, sigma=sigma, seed=seed)
    assert (max(values) - f(x0)) / gain >= 0.97


def test_noise_free_quadratic_2d_converges():
    """Noise-free correlated 2-D quadratic: within 100 evaluations a point within 1e-9 of the
    optimum is measured (conjugate directions make the parabola line searches exact)."""
    A = torch.tensor([[3.0, 2.5], [2.5, 3.0]], dtype=DT)
    c = torch.tensor([0.7, -0.4], dtype=DT)
    opt = RCDS(box(2, 2.0))
    drive(opt, lambda x: -float((x - c) @ A @ (x - c)), torch.tensor([-1.2, 1.0], dtype=DT), 100)
    assert float((opt.best()[0] - c).abs().max()) < 1e-9


def test_rosenbrock_2d_converges():
    """Noise-free Rosenbrock from (-1.2, 1): after 400 evaluations the best point is within 1e-3 of
    (1, 1) (needs the step halving when a cycle does not move)."""

    def neg_rosenbrock(x):
        return -float((1 - x[0]) ** 2 + 100 * (x[1] - x[0] ** 2) ** 2)

    opt = RCDS(box(2, 2.0))
    drive(opt, neg_rosenbrock, torch.tensor([-1.2, 1.0], dtype=DT), 400)
    assert torch.allclose(opt.best()[0], torch.ones(2, dtype=DT), atol=1e-3)


def test_conjugate_directions_solve_quadratic_in_one_cycle():
    """Given the quadratic's eigenvectors as directions, one cycle of exact line searches lands on
    the optimum: within 25 evaluations (3 knobs) a point within 1e-9 of it is measured."""
    g = np.random.default_rng(7)
    Q, _ = np.linalg.qr(g.standard_normal((3, 3)))
    A = torch.tensor(Q @ np.diag([1.0, 5.0, 20.0]) @ Q.T)
    c = torch.tensor([0.3, -0.2, 0.5], dtype=DT)
    opt = RCDS(box(3), directions=torch.tensor(Q))  # symmetric box: same axes in unit coordinates
    drive(opt, lambda x: float(-(x - c) @ A @ (x - c)), torch.zeros(3, dtype=DT), 25)
    assert float((opt.best()[0] - c).norm()) < 1e-9


def test_first_ask_steps_along_first_direction():
    """The first ask is x0 + step x range along the first (normalized) direction column."""
    bounds = torch.tensor([[0.0, 0.0], [2.0, 4.0]], dtype=DT)
    opt = RCDS(bounds, step=0.1, directions=[[1.0, 1.0], [1.0, -1.0]])
    x0 = torch.tensor([1.0, 2.0], dtype=DT)
    opt.tell(x0, 0.0)
    expected = x0 + 0.1 * torch.tensor([2.0, 4.0], dtype=DT) / 2**0.5
    assert torch.allclose(opt.ask(), expected, atol=1e-12)


def test_noise_parameter_helps_on_noisy_quadratic():
    """With noise sigma = 20 % of the gain on a 2-D quadratic, RCDS told the noise reaches >= 95 %
    of the gain in 60 evaluations on each of 10 seeds and beats noise=0 by >= 0.1 on average."""
    A = torch.tensor([[2.0, 1.5], [1.5, 2.0]], dtype=DT)
    c = torch.tensor([0.5, -0.3], dtype=DT)

    def f(x):
        return float(-(x - c) @ A @ (x - c))

    x0 = torch.zeros(2, dtype=DT)
    gain = -f(x0)
    sigma = 0.2 * gain
    fractions = {}
    for told in (0.0, sigma):
        fractions[told] = np.array(
            [
                (max(drive(RCDS(box(2), noise=told), f, x0, 60, sigma, seed)) + gain) / gain
                for seed in range(10)
            ]
        )
    assert fractions[sigma].min() >= 0.95
    assert fractions[sigma].mean() >= fractions[0.0].mean() + 0.1


@pytest.mark.parametrize("noise", [0.0, 0.005, 0.03])
def test_bracket_ends_lie_three_sigma_above_minimum(noise):
    """On f(t) = (t - 0.13)^2 along a line, both bracket ends (outermost points, or the start when
    the backward search is skipped) lie more than 3 sigma above the smallest bracket value, and the
    measured fitted minimum is exact."""
    u0, direction = np.array([0.3]), np.array([1.0])
    (u_min, f_min, n_eval), points = run_coroutine(
        line_minimize(u0, 0.0169, direction, 0.02, noise), lambda u: float((u[0] - 0.43) ** 2)
    )
    ts = np.array([p[0] for p in points[:-1]]) - 0.3  # the last point is the fitted minimum
    values = (ts - 0.13) ** 2
    smallest = min(values.min(), 0.0169)
    for end in (min(ts.min(), 0.0), ts.max()):
        assert (end - 0.13) ** 2 > smallest + 3 * noise
    assert u_min[0] == pytest.approx(0.43, abs=1e-9) == points[-1][0]
    assert f_min == pytest.approx(0.0, abs=1e-15)
    assert n_eval == len(points)
    if noise == 0.03:  # +-0.3 around the minimum needed, versus the first step 0.02 without noise
        assert ts.max() - min(ts.min(), 0.0) > 0.6


def test_bracket_stops_at_cube_face():
    """A line whose minimum lies beyond the cube's face samples the face and returns it."""
    (u_min, _, _), points = run_coroutine(
        line_minimize(np.array([0.5, 0.5]), 0.0, np.array([1.0, 0.0]), 0.05, 0.0),
        lambda u: -float(u[0]),
    )
    assert max(p[0] for p in points) == 1.0
    assert all(0.0 <= p[0] <= 1.0 for p in points)
    assert u_min[0] == 1.0


def test_fit_parabola_minimum_exact_and_outlier():
    """The fitted vertex is exact for parabola samples, ignores one large spike, and is None for a
    concave or flat sample set."""
    t = np.linspace(-1.0, 2.0, 9)
    f = 3.0 * (t - 0.4) ** 2 + 1.0
    assert fit_parabola_minimum(t, f, 0.0) == pytest.approx(0.4, abs=1e-12)
    spiked = f.copy()
    spiked[2] += 50.0
    assert fit_parabola_minimum(t, spiked, 0.01) == pytest.approx(0.4, abs=1e-9)
    assert fit_parabola_minimum(t, -f, 0.0) is None
    assert fit_parabola_minimum(t, np.ones_like(t), 0.0) is None
    assert fit_parabola_minimum(t[:2], f[:2], 0.0) is None


def test_powell_criterion():
    """Powell's test keeps the set when the extrapolated point is no better than the start, and
    replaces a direction for a long straight valley (f0 = 10, fm = 4, fe = 1, drop = 4)."""
    assert powell_keeps_directions(1.0, 0.5, 1.0, 0.5)
    # 2 (10 - 8 + 1)(10 - 4 - 4)^2 = 24 < (10 - 1)^2 * 4 = 324 -> replace
    assert not powell_keeps_directions(10.0, 4.0, 1.0, 4.0)
    # 2 (10 - 8 + 9)(10 - 4 - 0.1)^2 = 765.8 >= (10 - 9)^2 * 0.1 -> keep
    assert powell_keeps_directions(10.0, 4.0, 9.0, 0.1)


def test_maximize_and_minimize_are_symmetric():
    """Maximizing f and minimizing -f (same noise) ask exactly the same points."""
    f, _ = correlated_quadratic(3, 4)
    x0 = torch.full((3,), 0.3, dtype=DT)
    up, down = RCDS(box(3), noise=0.05), RCDS(box(3), noise=0.05, maximize=False)
    drive(up, f, x0, 80, sigma=0.05, seed=1)
    drive(down, lambda x: -f(x), x0, 80, sigma=-0.05, seed=1)
    assert torch.equal(torch.stack(up.X), torch.stack(down.X))
    assert torch.equal(up.best()[0], down.best()[0])


@settings(max_examples=40, deadline=None)
@given(data=st.data())
def test_asks_stay_inside_bounds(data):
    """Whatever finite values are told, every asked point lies inside the bounds."""
    d = data.draw(st.integers(1, 4))
    lo = np.array(data.draw(st.lists(st.floats(-10, 10), min_size=d, max_size=d)))
    width = np.array(data.draw(st.lists(st.floats(1e-3, 10), min_size=d, max_size=d)))
    bounds = torch.tensor(np.stack([lo, lo + width]), dtype=DT)
    frac = torch.tensor(data.draw(st.lists(st.floats(0, 1), min_size=d, max_size=d)), dtype=DT)
    ys = data.draw(
        st.lists(st.floats(allow_nan=False, allow_infinity=False), min_size=41, max_size=41)
    )
    opt = RCDS(
        bounds,
        noise=data.draw(st.floats(0, 10)),
        step=data.draw(st.floats(1e-3, 1.0)),
        maximize=data.draw(st.booleans()),
    )
    opt.tell(bounds[0] + frac * (bounds[1] - bounds[0]), ys[0])
    for y in ys[1:]:
        x = opt.ask()
        assert x.dtype == DT and x.shape == (d,)
        assert bool((x >= bounds[0]).all() and (x <= bounds[1]).all())
        opt.tell(x, y)


def test_protocol_errors():
    """ask before the start point, a told point other than the asked one, a wrong dimension and a
    tell without a pending ask are refused with clear errors."""
    opt = RCDS(box(2))
    with pytest.raises(RuntimeError, match="start point"):
        opt.ask()
    with pytest.raises(ValueError, match="2 knobs"):
        opt.tell(torch.zeros(1, dtype=DT), 1.0)
    opt.tell(torch.zeros(2, dtype=DT), 1.0)
    with pytest.raises(ValueError, match="call ask"):
        opt.tell(torch.zeros(2, dtype=DT), 1.0)
    x = opt.ask()
    with pytest.raises(ValueError, match="differs from the asked point"):
        opt.tell(torch.zeros(2, dtype=DT), 1.0)
    with pytest.raises(ValueError, match="2 knobs"):
        opt.tell(x[:1], 1.0)
    opt.tell(x, 2.0)
    assert opt.n_told == 2 and opt.best()[1] == 2.0


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"noise": -1.0}, "noise"),
        ({"noise": float("inf")}, "noise"),
        ({"step": 0.0}, "step"),
        ({"step": 1.5}, "step"),
        ({"directions": np.eye(3)}, "shape"),
        ({"directions": [[1.0, 2.0], [2.0, 4.0]]}, "linearly independent"),
        ({"directions": [[1.0, 0.0], [0.0, 0.0]]}, "zero column"),
        ({"directions": [[1.0, float("nan")], [0.0, 1.0]]}, "NaN"),
    ],
)
def test_bad_settings_rejected(kwargs, match):
    """Out-of-range settings and degenerate direction sets raise ValueError naming the problem."""
    with pytest.raises(ValueError, match=match):
        RCDS(box(2), **kwargs)
