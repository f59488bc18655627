"""Nelder–Mead restarted at a fixed period from the re-measured best setting."""

from __future__ import annotations

import pytest
import torch

from pigp_torch.methods import METHODS, RunContext
from pigp_torch.optimizers import NelderMead
from pigp_torch.optimizers.nm_restart import DEFAULT_PERIOD, NelderMeadRestart
from tests.optimizers.problems import box

DT = torch.float64


def run(opt, f_t, x0, readings: int) -> list[float]:
    """Drive ``opt`` on the time-dependent ``f_t(x, t)`` (t = reading index); true values."""
    opt.tell(x0, f_t(x0, 0))
    for t in range(1, readings):
        x = opt.ask()
        opt.tell(x, f_t(x, t))
    return opt.Y


def sinking(x, t):
    """A peak moving from 0.3 by 0.01 per reading whose height falls by 0.05 per reading: old
    readings look better than they are now."""
    return float(-((x - 0.3 - 0.01 * t) ** 2).sum()) - 0.05 * t


def test_restarts_at_the_period_from_the_segment_best_re_measured():
    opt = NelderMeadRestart(box(3), period=10)
    run(opt, sinking, torch.zeros(3, dtype=DT), 35)
    assert [n for n, _, _ in opt.restarts] == [10, 20, 30]
    for n, x, y in opt.restarts:
        seg = range(n - 10, n)  # the segment before the restart, its opening reading included
        i = max(seg, key=lambda j: opt.Y[j])
        assert torch.equal(x, opt.X[i]) and torch.equal(opt.X[n], opt.X[i])
        assert y == pytest.approx(sinking(x, n))  # the value is fresh, not the stored one
    # the stale best (largest stored value) is in segment 0, yet a later restart starts elsewhere
    stale = max(range(len(opt.Y)), key=lambda j: opt.Y[j])
    assert stale < 10 and not torch.equal(opt.restarts[-1][1], opt.X[stale])


def test_recommend_is_the_latest_re_measured_setting():
    opt = NelderMeadRestart(box(2), period=6)
    run(opt, sinking, torch.zeros(2, dtype=DT), 5)
    assert torch.equal(opt.recommend(), opt.best()[0])  # no restart yet
    run_more = [opt.tell(x, sinking(x, t)) for t in range(5, 14) for x in [opt.ask()]]
    assert len(run_more) == 9 and [n for n, _, _ in opt.restarts] == [6, 12]
    assert torch.equal(opt.recommend(), opt.restarts[-1][1])


def test_bounds_hold_with_the_optimum_outside_the_box():
    bounds = torch.tensor([[-1.0, 0.0, 2.0], [1.0, 0.5, 3.0]], dtype=DT)
    opt = NelderMeadRestart(bounds, period=7, initial_simplex_size=0.5)
    run(opt, lambda x, t: float(-((x - 5.0 - 0.1 * t) ** 2).sum()), bounds.mean(0), 60)
    X = torch.stack(opt.X)
    assert bool((X >= bounds[0]).all() and (X <= bounds[1]).all())
    assert X[:, 0].max() == 1.0  # it reached the upper bound of the first knob


def test_follows_a_moving_peak_better_than_plain_nelder_mead():
    def moving(x, t):  # the peak walks from -0.5 to +0.5 over 300 readings
        return float(-((x - (-0.5 + t / 300.0)) ** 2).sum())

    x0 = torch.full((4,), -0.5, dtype=DT)
    late = slice(150, 300)
    plain = run(NelderMead(box(4)), moving, x0, 300)[late]
    restart = run(NelderMeadRestart(box(4), period=30), moving, x0, 300)[late]
    assert sum(restart) / len(restart) > 2 * sum(plain) / len(plain)  # values are negative


def test_period_must_allow_a_step_and_registry_defaults():
    with pytest.raises(ValueError, match="period must be an integer >= d \\+ 2 = 5"):
        NelderMeadRestart(box(3), period=4)
    opt = METHODS["nelder-mead-restart"].build(RunContext(knob_bounds=box(3)))
    plain = METHODS["nelder-mead"].build(RunContext(knob_bounds=box(3)))
    assert isinstance(opt, NelderMeadRestart) and opt.period == DEFAULT_PERIOD == 50
    assert (opt.initial_simplex_size, opt.adaptive) == (plain.initial_simplex_size, plain.adaptive)
    assert opt.maximize and opt.name == "nelder-mead-restart"
