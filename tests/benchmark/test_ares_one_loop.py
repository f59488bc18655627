"""The ARES benchmark runs through the one loop (:func:`pigp_torch.loop.optimize`) and gives the
numbers of a plain ask -> set -> read -> tell loop to the bit."""

from __future__ import annotations

import pandas as pd
import pytest
import torch

pytest.importorskip("cheetah")

import pigp_torch.machines.ares_ea.benchmark as bench
from pigp_torch.machines.ares_ea.benchmark import STEP_COLUMNS, check_ares_methods, run_ares_trial
from pigp_torch.machines.ares_ea.simulation import load_trials


@pytest.fixture(scope="module")
def trials():
    return load_trials()


def plain_loop(trial, method: str, steps: int, noise: float, seed: int) -> pd.DataFrame:
    """The benchmark's rows from a hand-written loop: no ramps, checks or retries."""
    (spec,) = check_ares_methods([method])
    machine, ctx = bench._trial_machine(trial, spec, noise, seed, None, "none")
    rows = []

    def record(step):
        obs, true = machine.last_observables, machine.true_observables(machine.get())
        rows.append([trial.index, spec.name, step, *obs.tolist(), float(machine.mae(obs)),
                     float(machine.mae(true)), "none"])  # fmt: skip

    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        opt = spec.build(ctx)
        for step in range(steps):
            if step > 0:
                machine.set(opt.ask())
            y = machine.read()
            if opt.uses_observables:
                opt.tell(machine.get(), y, observables=machine.last_observables)
            else:
                opt.tell(machine.get(), y)
            record(step)
        x_final = opt.recommend()
    machine.set(x_final)
    machine.read()
    record(steps)
    return pd.DataFrame(rows, columns=list(STEP_COLUMNS))


@pytest.mark.parametrize(("method", "noise"), [("nelder-mead", 0.0), ("ares-physics", 1e-5)])
def test_the_one_loop_gives_the_plain_loops_numbers(trials, method, noise):
    """Through ``optimize`` (checked moves and readings, no stated noise: no re-reads) the
    per-step table equals the plain loop's exactly: same asks, readings and set-back."""
    a = run_ares_trial(trials[1], method, steps=6, noise=noise, seed=3)
    b = plain_loop(trials[1], method, 6, noise, 3)
    pd.testing.assert_frame_equal(a, b, check_exact=True)


def test_each_run_is_one_optimize_call(trials, monkeypatch):
    """A run calls the loop once for its ``steps`` evaluations (the knobs left where the last
    step put them), then sets back to the method's recommended setting: ``steps + 1`` rows."""
    calls = []
    real = bench.optimize

    def spy(machine, optimizer, x0, budget, **kw):
        table = real(machine, optimizer, x0, budget, **kw)
        calls.append((budget, kw["restore"], kw["method"], table))
        return table

    monkeypatch.setattr(bench, "optimize", spy)
    df = run_ares_trial(trials[2], "published-nm", steps=5, seed=2)
    assert [(b, r, m) for b, r, m, _ in calls] == [(5, "none", "published-nm")]
    assert calls[0][3]["step"].tolist() == [0, 1, 2, 3, 4]
    assert df["step"].tolist() == [0, 1, 2, 3, 4, 5]


def test_a_noise_free_ares_physics_run_sets_back_to_its_best_reading(trials):
    """Noise-free screen, the model passes its check: the set-back (``recommend()``) is the best
    reading's setting, so its row reads that reading's beam to the bit (today's set-back)."""
    df = run_ares_trial(trials[1], "ares-physics", steps=8, seed=0)
    steps = df[df["step"] < 8]
    best = steps.loc[steps["mae"].idxmin()]
    final = df[df["step"] == 8].iloc[0]
    cols = ["mu_x", "sigma_x", "mu_y", "sigma_y", "mae", "mae_true"]
    assert final[cols].tolist() == best[cols].tolist()
