"""Screen noise (``--noise``, m per beam number) on every method that runs on the ARES machine."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import torch

pytest.importorskip("cheetah")

from pigp_torch.cli import main
from pigp_torch.machines.ares_ea.benchmark import check_ares_methods, run_ares_trial, score_runs
from pigp_torch.machines.ares_ea.machine import AresMachine
from pigp_torch.machines.ares_ea.simulation import load_trials
from pigp_torch.methods import METHODS, RunContext

NOISE = 5e-6  # m, the noisy benchmark's screen noise
FAST = ["published-bo", "published-nm", "ml2"]


@pytest.fixture(scope="module")
def trials():
    return load_trials()


def check_noisy_run(df, steps: int) -> None:
    """Readings carry the stated noise, the scores use the noise-free beam."""
    assert len(df) == steps + 1
    dev = (df["mae"] - df["mae_true"]).to_numpy()
    # |MAE(o + e) - MAE(o)| <= mean |e|: 5 um noise on 4 numbers stays far below 30 um ...
    assert np.abs(dev).max() < 6 * NOISE
    # ... and it is there: every reading differs from the truth, by about a noise sigma or less
    assert (dev != 0).all()
    assert 0.1 * NOISE < np.sqrt(np.mean(dev**2)) < 2 * NOISE
    s = score_runs(df).iloc[0]
    assert s["final_mae"] == df.loc[df["step"] == steps, "mae_true"].iloc[0]
    assert s["best_mae"] == df.loc[df["step"] < steps, "mae_true"].min()


def test_every_ares_method_is_checked():
    """The methods built for ARES are all covered here (fast ones below, ares-physics slow)."""
    ares = {n for n, s in METHODS.items() if s.machine == "ares-ea"}
    assert ares <= {*FAST, "ares-physics"}


@pytest.mark.parametrize("method", FAST)
def test_noise_on_the_scalar_methods(trials, method):
    """published-bo, published-nm and ML-II (GPyTorch ARD GP, the reward objective) run with 5 um
    screen noise; the same seed without noise reads the true beam."""
    df = run_ares_trial(trials[1], method, steps=6, noise=NOISE, seed=1)
    check_noisy_run(df, 6)
    clean = run_ares_trial(trials[1], method, steps=3, noise=0.0, seed=1)
    assert (clean["mae"] == clean["mae_true"]).all()


@pytest.mark.slow
def test_noise_on_ares_physics(trials):
    """ares-physics fits the four noisy numbers with the stated screen noise as its noise."""
    df = run_ares_trial(trials[1], "ares-physics", steps=5, noise=NOISE, seed=1)
    check_noisy_run(df, 5)
    m = AresMachine(trials[1], objective="mae", noise=NOISE)
    opt = METHODS["ares-physics"].build(RunContext(machine=m, noise=NOISE, maximize=False))
    assert opt.obs_sd == NOISE


def test_methods_needing_a_ring_prior_are_refused(tmp_path, capsys):
    """pigp-physics (a method that needs a ring's physics prior, whose peak form is the ring's)
    cannot run on ARES: one line, exit 2, before any run."""
    with pytest.raises(ValueError, match="needs a ring's physics prior"):
        check_ares_methods(["published-bo", "pigp-physics"])
    rc = main(
        ["bench", "ares", "--trial-ids", "0", "--methods", "pigp-physics", "-o", str(tmp_path)]
    )
    assert rc == 2
    assert "needs a ring's physics prior" in capsys.readouterr().err
    assert not (tmp_path / "steps.csv").exists()


def test_runs_repeat_to_the_bit(trials):
    """published-bo (BoTorch draws from torch's global generator) repeats to the bit for one
    seed, whatever the global generator's state before, which the run leaves as it found it."""
    torch.manual_seed(123)
    a = run_ares_trial(trials[5], "published-bo", steps=10, seed=5)
    state = torch.random.get_rng_state()
    torch.manual_seed(456)
    b = run_ares_trial(trials[5], "published-bo", steps=10, seed=5)
    pd.testing.assert_frame_equal(a, b)
    torch.manual_seed(123)
    run_ares_trial(trials[5], "published-bo", steps=10, seed=5)
    assert torch.equal(torch.random.get_rng_state(), state)
