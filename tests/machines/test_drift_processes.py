"""The shared drift processes (pigp_torch.machines.drift): paths, play hysteresis, the moving
optimum, the run driver and the window scores, on closed-form cases."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from pigp_torch.machines.drift import (
    DriftPath,
    PlayHysteresis,
    drive,
    interpolate_track,
    optimum_track,
    window_statistic,
)
from pigp_torch.optimizers import AskTellOptimizer


def test_linear_path_is_rate_times_reading():
    p = DriftPath(rate=[1e-6, -2e-6])
    for t in (0, 1, 7, 300):
        assert torch.allclose(p(t), torch.tensor([1e-6 * t, -2e-6 * t], dtype=torch.float64))


def test_walk_is_one_function_of_the_reading_whatever_the_order_and_horizon():
    a = DriftPath(walk_sd=[1.0, 2.0], seed=5, horizon=10)
    late = a(2000)  # drawn on demand past the horizon
    b = DriftPath(walk_sd=[1.0, 2.0], seed=5, horizon=4000)
    # the same increments; the running sums of two chunkings agree to rounding
    assert torch.allclose(a(17), b(17), rtol=1e-12, atol=0)
    assert torch.allclose(late, b(2000), rtol=1e-12, atol=0)
    assert torch.equal(a(17), DriftPath(walk_sd=[1.0, 2.0], seed=5, horizon=10)(17))
    assert not torch.allclose(DriftPath(walk_sd=[1.0, 2.0], seed=6)(17), b(17))
    assert torch.equal(b(0), torch.zeros(2, dtype=torch.float64))


def test_walk_increments_have_the_stated_sd():
    q = 2e-6
    p = DriftPath(walk_sd=[q] * 200, seed=1)
    steps = torch.stack([p(t) for t in range(301)]).diff(dim=0)  # 300 x 200 increments
    assert float(steps.std()) == pytest.approx(q, rel=0.03)
    assert float(p(300).std()) == pytest.approx(q * math.sqrt(300), rel=0.2)


def test_step_happens_at_the_stated_reading():
    p = DriftPath(step=[5.0, -1.0], step_at=150)
    assert torch.equal(p(149), torch.zeros(2, dtype=torch.float64))
    assert torch.equal(p(150), torch.tensor([5.0, -1.0], dtype=torch.float64))
    assert torch.equal(p(400), p(150))


@pytest.mark.parametrize(
    "kwargs", [{}, {"rate": [1.0], "walk_sd": [1.0, 2.0]}, {"walk_sd": [-1.0]}]
)
def test_bad_paths_are_refused(kwargs):
    with pytest.raises(ValueError):
        DriftPath(**kwargs)


def test_play_hysteresis_closed_form():
    w = 0.5
    up = PlayHysteresis([w], [0.0])
    assert float(up.apply([2.0])[0]) == pytest.approx(2.0 - w)  # pushed up: lags by w
    assert float(up.apply([1.0])[0]) == pytest.approx(1.0 + w)  # came down to 1: x + w
    fresh = PlayHysteresis([w], [0.0])
    assert float(fresh.apply([1.0])[0]) == pytest.approx(1.0 - w)  # came up to 1: x - w
    # same setpoint, different history -> acting fields 2w apart
    assert float(up.y[0] - fresh.y[0]) == pytest.approx(2 * w)
    # inside the play band nothing moves; acting() does not change the state
    assert float(up.apply([1.3])[0]) == pytest.approx(1.5)
    assert torch.allclose(up.acting(torch.tensor([[3.0], [1.2]])).squeeze(), torch.tensor(
        [2.5, 1.5], dtype=torch.float64))  # fmt: skip
    assert float(up.y[0]) == pytest.approx(1.5)
    none = PlayHysteresis([0.0], [0.3])
    assert float(none.apply([0.7])[0]) == 0.7  # width 0: the setpoint acts


def test_optimum_track_follows_a_moving_peak():
    c = torch.tensor([0.01, -0.02], dtype=torch.float64)

    def f_at(t):
        return lambda X: 1.0 + 0.001 * t - ((X - c * t) ** 2).sum(-1)

    bounds = torch.tensor([[-5.0, -5.0], [5.0, 5.0]], dtype=torch.float64)
    times, X, F = optimum_track(f_at, bounds, range(0, 101, 25), n_starts=2)
    assert list(times) == [0, 25, 50, 75, 100]
    assert torch.allclose(X, torch.stack([c * t for t in times]), atol=1e-5)
    assert np.allclose(F, 1.0 + 0.001 * times, atol=1e-8)
    assert np.allclose(interpolate_track(times, F, [10, 60]), [1.01, 1.06], atol=1e-8)


class _Toy:
    """A 1-knob machine reading -(x - 1)^2, whose true observable is x."""

    def __init__(self):
        self.x = torch.zeros(1, dtype=torch.float64)
        self.last_observables = self.last_true_observables = None

    def set(self, x):
        self.x = torch.as_tensor(x, dtype=torch.float64).reshape(1).clone()

    def get(self):
        return self.x.clone()

    def read(self):
        self.last_observables = self.last_true_observables = self.x.clone()
        return float(-((self.x - 1) ** 2))


class _Grid(AskTellOptimizer):
    """Asks 0.5, 1.0, 2.0, ...; best() is the best told (and so ``recommend()``, the default)."""

    def __init__(self):
        super().__init__(torch.tensor([[0.0], [4.0]], dtype=torch.float64))
        self.asks, self.told = iter([0.5, 1.0, 2.0, 3.0]), []

    def ask(self):
        return torch.tensor([next(self.asks)], dtype=torch.float64)

    def tell(self, x, y):
        self.told.append((float(x[0]), y))

    def best(self):
        x, y = max(self.told, key=lambda p: p[1])
        return torch.tensor([x], dtype=torch.float64), y


def test_drive_reads_asks_and_sets_back_to_the_best():
    X, true = drive(_Toy(), _Grid(), 4)
    assert X[:, 0].tolist() == [0.0, 0.5, 1.0, 2.0, 1.0]  # 4 readings + the set-back
    assert torch.equal(true, X)
    with pytest.raises(ValueError):
        drive(_Toy(), _Grid(), 0)


def test_window_statistic_closed_form():
    v = list(range(10))
    assert window_statistic(v, (2, 6)) == 3.5  # median of 2, 3, 4, 5
    assert window_statistic(v, (0, 10), "mean") == 4.5
    with pytest.raises(ValueError):
        window_statistic(v, (20, 30))
    with pytest.raises(ValueError):
        window_statistic(v, (0, 3), "max")
