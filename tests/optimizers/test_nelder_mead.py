"""Tests for the ask/tell Nelder–Mead optimizer."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from pigp_torch.optimizers.nelder_mead import NelderMead

from .problems import DT, box, correlated_quadratic, drive


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_noisy_quadratic_5d_gain_fraction(seed):
    """On a correlated 5-D quadratic (condition 20) with noise 1 % of the gain, 300 evaluations
    reach >= 95 % of the possible noise-free gain."""
    f, _ = correlated_quadratic(5, seed)
    x0 = torch.zeros(5, dtype=DT)
    gain = 0.0 - f(x0)
    values = drive(NelderMead(box(5)), f, x0, 300, sigma=0.01 * gain, seed=seed)
    fraction = (max(values) - f(x0)) / gain
    assert fraction >= 0.95


def test_rosenbrock_2d_converges():
    """Noise-free Rosenbrock from (-1.2, 1): the best point is within 1e-3 of the optimum (1, 1)."""

    def neg_rosenbrock(x):
        return -float((1 - x[0]) ** 2 + 100 * (x[1] - x[0] ** 2) ** 2)

    opt = NelderMead(box(2, 2.0))
    drive(opt, neg_rosenbrock, torch.tensor([-1.2, 1.0], dtype=DT), 400)
    x_best, y_best = opt.best()
    assert torch.allclose(x_best, torch.ones(2, dtype=DT), atol=1e-3)
    assert y_best > -1e-6


def test_initial_simplex_steps_each_knob_towards_room():
    """The first d asks move one knob each by initial_simplex_size x range, towards the far side."""
    bounds = torch.tensor([[0.0, -2.0, 10.0], [1.0, 2.0, 20.0]], dtype=DT)
    opt = NelderMead(bounds, initial_simplex_size=0.1)
    x0 = torch.tensor([0.2, 1.5, 15.0], dtype=DT)  # knob 1 in its upper half -> step down
    opt.tell(x0, 0.0)
    steps = [0.1, -0.4, 1.0]
    for i, s in enumerate(steps):
        x = opt.ask()
        expected = x0.clone()
        expected[i] += s
        assert torch.allclose(x, expected, atol=1e-12)
        opt.tell(x, -1.0)


@pytest.mark.parametrize(("adaptive", "gamma"), [(True, 1.0 + 2.0 / 2), (False, 2.0)])
def test_reflection_and_expansion_points(adaptive, gamma):
    """With the worst vertex known, the next asks are the reflection 2c - w and, when it is the best
    point so far, the expansion c + gamma (c - w) (gamma = 1 + 2/d adaptive, 2 classical)."""
    opt = NelderMead(box(2), initial_simplex_size=0.25, adaptive=adaptive)
    x0 = torch.tensor([-0.5, -0.5], dtype=DT)
    opt.tell(x0, 0.0)  # worst (maximizing)
    v1 = opt.ask()
    opt.tell(v1, 2.0)
    v2 = opt.ask()
    opt.tell(v2, 1.0)
    centroid = (v1 + v2) / 2
    reflected = opt.ask()
    assert torch.allclose(reflected, 2 * centroid - x0, atol=1e-12)
    opt.tell(reflected, 5.0)  # best so far -> expansion
    assert torch.allclose(opt.ask(), centroid + gamma * (centroid - x0), atol=1e-12)


def test_restart_remeasures_best_point():
    """After the simplex converges (xatol), the optimizer asks for the best point again and then
    builds a fresh simplex of the initial size around it."""
    f, c = correlated_quadratic(2, 3)
    opt = NelderMead(box(2), initial_simplex_size=0.05, xatol=1e-2)
    opt.tell(torch.zeros(2, dtype=DT), f(torch.zeros(2, dtype=DT)))
    for _ in range(300):
        x_best, _ = opt.best()
        x = opt.ask()
        if torch.equal(x, x_best):
            break
        opt.tell(x, f(x))
    else:
        pytest.fail("no restart within 300 evaluations")
    opt.tell(x, f(x))
    first_vertex = opt.ask()
    step = (first_vertex - x).abs()
    assert torch.allclose(step, torch.tensor([0.1, 0.0], dtype=DT), atol=1e-12)
    assert torch.allclose(x, c, atol=0.05)


def test_maximize_and_minimize_are_symmetric():
    """Maximizing f and minimizing -f (same noise) ask exactly the same points."""
    f, _ = correlated_quadratic(3, 4)
    x0 = torch.full((3,), 0.3, dtype=DT)
    up, down = NelderMead(box(3)), NelderMead(box(3), maximize=False)
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
    size = data.draw(st.floats(1e-3, 0.5))
    ys = data.draw(
        st.lists(st.floats(allow_nan=False, allow_infinity=False), min_size=41, max_size=41)
    )
    opt = NelderMead(
        bounds, initial_simplex_size=size, maximize=data.draw(st.booleans()), xatol=1e-2
    )
    opt.tell(bounds[0] + frac * (bounds[1] - bounds[0]), ys[0])
    for y in ys[1:]:
        x = opt.ask()
        assert x.dtype == DT and x.shape == (d,)
        assert bool((x >= bounds[0]).all() and (x <= bounds[1]).all())
        opt.tell(x, y)


def test_protocol_errors():
    """ask before the start point, a told point other than the asked one, a wrong dimension, a tell
    without a pending ask and a start outside the bounds are refused with clear errors."""
    opt = NelderMead(box(2))
    with pytest.raises(RuntimeError, match="start point"):
        opt.ask()
    with pytest.raises(ValueError, match="outside the bounds"):
        opt.tell(torch.tensor([0.0, 1.5], dtype=DT), 1.0)
    with pytest.raises(ValueError, match="2 knobs"):
        opt.tell(torch.zeros(3, dtype=DT), 1.0)
    opt.tell(torch.zeros(2, dtype=DT), 1.0)
    with pytest.raises(ValueError, match="call ask"):
        opt.tell(torch.zeros(2, dtype=DT), 1.0)
    x = opt.ask()
    assert torch.equal(opt.ask(), x)  # asking again repeats the pending point
    with pytest.raises(ValueError, match="differs from the asked point"):
        opt.tell(x + 1e-3, 1.0)
    with pytest.raises(ValueError, match="finite"):
        opt.tell(x, float("nan"))
    opt.tell(x + 1e-12, 1.0)  # within tolerance
    assert opt.n_told == 2


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"initial_simplex_size": 0.0}, "initial_simplex_size"),
        ({"initial_simplex_size": 0.7}, "initial_simplex_size"),
        ({"xatol": -1.0}, "xatol"),
        ({"fatol": float("nan")}, "fatol"),
    ],
)
def test_bad_settings_rejected(kwargs, match):
    """Out-of-range settings raise ValueError naming the setting."""
    with pytest.raises(ValueError, match=match):
        NelderMead(box(2), **kwargs)
