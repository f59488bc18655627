"""The ARES-EA machine, the published recipes and ``pigp bench ares``."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pandas as pd
import pytest
import torch

pytest.importorskip("cheetah")

from pigp_torch.cli import main
from pigp_torch.machine import Machine
from pigp_torch.machines.ares_ea.benchmark import score_runs, summarize_scores
from pigp_torch.machines.ares_ea.machine import AresMachine, ares_objective
from pigp_torch.machines.ares_ea.simulation import (
    START_SETTING,
    AresSegment,
    knob_bounds,
    load_trials,
)
from pigp_torch.methods import METHODS, RunContext

D = torch.float64


@pytest.fixture(scope="module")
def trials():
    return load_trials()


def test_machine_reads_objective_and_observables(trials):
    """The machine follows the protocol, keeps the four numbers it read, and its objectives are
    the stated functions of them."""
    t = trials[5]
    m = AresMachine(t, objective="mae")
    assert isinstance(m, Machine) and not m.maximize
    y = m.read()
    obs = m.last_observables
    assert obs.shape == (4,)
    seg = AresSegment()
    torch.testing.assert_close(
        obs, seg.observe(torch.tensor(START_SETTING, dtype=D), t.incoming, t.misalignments)
    )
    assert y == pytest.approx(float((obs - t.target).abs().mean()), rel=1e-12)
    r = AresMachine(t, objective="reward", segment=seg)
    assert r.maximize
    assert r.read() == pytest.approx(
        10.0 - math.log(float((obs - t.target).abs().sum())), rel=1e-12
    )


def test_objective_off_screen():
    """Off the screen the reward loses 20 and the distance is 100 times larger."""
    obs = torch.tensor([[1e-3, 1e-4, 0.0, 1e-4], [1e-3, 1e-4, 0.0, 1e-4]], dtype=D)
    target = torch.zeros(4, dtype=D)
    on = torch.tensor([True, False])
    r = ares_objective(obs, target, on, "reward")
    assert float(r[0] - r[1]) == pytest.approx(20.0)
    d = ares_objective(obs, target, on, "distance")
    assert float(d[1] / d[0]) == pytest.approx(100.0)
    with pytest.raises(ValueError, match="unknown ARES objective"):
        ares_objective(obs, target, on, "nope")


def test_machine_noise_is_stated_gaussian(trials):
    """Screen noise of 5 um gives readings whose deviation from the true beam has that rms."""
    m = AresMachine(trials[2], objective="mae", noise=5e-6, seed=3)
    true = m.true_observables(m.get())
    dev = torch.stack([m.read_observables() - true for _ in range(400)])
    assert float(dev[:, 0].std()) == pytest.approx(5e-6, rel=0.15)
    assert float(dev[:, 2].mean()).__abs__() < 1.5e-6
    with pytest.raises(ValueError, match="noise"):
        AresMachine(trials[2], noise=-1.0)


def test_published_bo_samples_in_boxes(trials):
    """The published BO starts at [10, -10, 0, 10, 0], samples 4 points within 0.05 of each
    range around it, then stays within the same box around the last sample, and keeps the
    quadrupoles unidirectional."""
    m = AresMachine(trials[0])
    opt = METHODS["published-bo"].build(RunContext(machine=m, seed=1))
    uni = knob_bounds(unidirectional=True)
    half = 0.05 * (uni[1] - uni[0])
    x0 = torch.tensor(START_SETTING, dtype=D)
    torch.testing.assert_close(opt.ask(), x0)
    xs = []
    for _ in range(8):
        x = opt.ask() if xs else x0
        opt.tell(x, m(x))
        xs.append(x)
    for x in xs[1:5]:
        assert ((x - x0).abs() <= half * (1 + 1e-9)).all()
    for prev, x in itertools.pairwise(xs[4:]):
        assert ((x - prev).abs() <= half * (1 + 1e-9)).all()
    X = torch.stack(xs)
    assert (X >= uni[0]).all() and (X <= uni[1]).all()


def test_bench_ares_command(tmp_path, trials, capsys):
    """``pigp bench ares`` on 2 trials writes the per-step CSV with the stated columns, mae is the
    mean |reading - target|, the set-back row is the best setting's beam, and the summary
    matches the per-step table."""
    out = tmp_path / "ares"
    rc = main(
        [
            "bench", "ares", "--trial-ids", "50-51", "--methods", "published-bo", "published-nm",
            "--steps", "8", "--noise", "2e-6", "-o", str(out), "--quiet",
        ]
    )  # fmt: skip
    assert rc == 0
    df = pd.read_csv(out / "steps.csv")
    assert list(df.columns[:8]) == [
        "trial", "method", "step", "mu_x", "sigma_x", "mu_y", "sigma_y", "mae",
    ]  # fmt: skip
    assert set(df["trial"]) == {50, 51} and set(df["method"]) == {"published-bo", "published-nm"}
    assert len(df) == 2 * 2 * 9
    for tid in (50, 51):
        tgt = trials[tid].target.numpy()
        sub = df[df["trial"] == tid]
        obs = sub[["mu_x", "sigma_x", "mu_y", "sigma_y"]].to_numpy()
        np.testing.assert_allclose(sub["mae"], np.abs(obs - tgt).mean(axis=1), rtol=1e-12)
        # noise of 2 um: reading and noise-free MAE differ, by at most a few noise sigmas
        assert (sub["mae"] != sub["mae_true"]).any()
        assert (sub["mae"] - sub["mae_true"]).abs().max() < 10e-6
    # start: the same beam for both methods (noise-free MAE)
    starts = df[df["step"] == 0].groupby("trial")["mae_true"].nunique()
    assert (starts == 1).all()
    scores = score_runs(df)
    for _, r in scores.iterrows():
        run = df[(df["method"] == r["method"]) & (df["trial"] == r["trial"])]
        assert r["best_mae"] == pytest.approx(run.loc[run["step"] < 8, "mae_true"].min())
    summary = pd.read_csv(out / "summary.csv")
    assert list(summary["method"]) == list(summarize_scores(scores)["method"])
    assert (out / "mae_vs_step.png").stat().st_size > 1000
    text = capsys.readouterr().out
    assert "final MAE um" in text and "published-nm" in text


def test_bench_ares_errors(tmp_path, capsys):
    """Unknown trial ids and bad ranges end with a one-line error and exit code 2."""
    assert main(["bench", "ares", "--trial-ids", "400", "-o", str(tmp_path)]) == 2
    assert "not in" in capsys.readouterr().err
    assert main(["bench", "ares", "--trial-ids", "9-3", "-o", str(tmp_path)]) == 2


def test_default_methods_are_ours_and_the_published():
    """Without --methods the bench runs the physics method and the two published recipes."""
    from pigp_torch.machines.ares_ea.benchmark import default_ares_methods

    assert default_ares_methods() == ["ares-physics", "published-bo", "published-nm"]


@pytest.mark.slow
def test_ares_physics_reaches_target_on_a_tuning_trial(trials):
    """On tuning trial 3 (noise-free) the online-fitted model brings the beam within 20 um of the
    target in 12 readings, from about 600 um at the start."""
    from pigp_torch.machines.ares_ea.benchmark import run_ares_trial

    df = run_ares_trial(trials[3], "ares-physics", steps=12, seed=3)
    assert df["mae_true"].iloc[0] > 300e-6
    assert df["mae_true"].min() < 20e-6
    assert df["mae_true"].iloc[-1] == pytest.approx(df.loc[df["step"] < 12, "mae_true"].min())
