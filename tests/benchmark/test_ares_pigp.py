"""The paper's PI-GP on ARES-EA: the prior of the ARES model for a trial's target."""

from __future__ import annotations

import pandas as pd
import pytest
import torch

pytest.importorskip("cheetah")

from pigp_torch.cli import main
from pigp_torch.machines.ares_ea.benchmark import check_ares_methods
from pigp_torch.machines.ares_ea.command import ARES_PRIOR_METHODS_HELP
from pigp_torch.machines.ares_ea.machine import AresMachine
from pigp_torch.machines.ares_ea.prior import (
    ARES_PRIOR_METHODS,
    ARES_PRIOR_OBJECTIVE,
    PRIOR_NOISE_FLOOR_UM,
    ares_model_um,
    ares_prior,
    prior_noise,
)
from pigp_torch.machines.ares_ea.simulation import START_SETTING, load_trials

TRIAL = 3  # a tuning trial (0-49)


@pytest.fixture(scope="module")
def trials():
    return load_trials()


def test_prior_methods_are_accepted_and_read_minus_the_mae_in_um(trials):
    """pigp and pigp-fast pass the ARES check; their objective is minus the MAE in um,
    maximized; the prior's noise is half the screen noise (um), at least the floor."""
    assert [s.name for s in check_ares_methods(["pigp", "pigp-fast", "ml2"])] == [
        "pigp",
        "pigp-fast",
        "ml2",
    ]
    m = AresMachine(trials[TRIAL], objective=ARES_PRIOR_OBJECTIVE)
    assert m.maximize
    m.set(torch.tensor(START_SETTING, dtype=torch.float64))
    y = m.read()
    mae = float(m.mae(m.last_observables))
    assert mae > 1e-5
    assert y == pytest.approx(-1e6 * mae, rel=1e-12)
    assert prior_noise(0.0) == PRIOR_NOISE_FLOOR_UM
    assert prior_noise(5e-6) == pytest.approx(2.5)
    assert prior_noise(1e-7) == PRIOR_NOISE_FLOOR_UM
    assert ARES_PRIOR_METHODS_HELP == ARES_PRIOR_METHODS  # what --help names


def test_help_names_the_prior_methods(capsys):
    """`pigp bench ares --help` says which methods run with the ARES model's prior."""
    with pytest.raises(SystemExit):
        main(["bench", "ares", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "pigp, pigp-fast run with the paper's physics prior from the ARES model" in text


@pytest.mark.slow
def test_prior_peaks_where_the_model_goal_is_smallest(trials):
    """The prior's x0 is where the model's goal (smoothed MAE in um, unknowns at their centre)
    is smallest: below the goal at 512 random settings and at the start; f_x0 = -goal(x0),
    f_inf below it; the precision is symmetric positive definite; the noise is the floor for a
    noise-free screen (the bench test below reuses this cached prior)."""
    target = trials[TRIAL].target
    prior = ares_prior(target, 0.0)
    model = ares_model_um(target)
    theta = model.unknown_center
    b = model.bounds
    gen = torch.Generator().manual_seed(0)
    X = b[0] + (b[1] - b[0]) * torch.rand(512, model.dim, generator=gen, dtype=torch.float64)
    with torch.no_grad():
        g0 = float(model.goal_at(prior.x0[None], theta))
        g_rand = model.goal_at(X, theta)
        g_start = float(model.goal_at(torch.tensor([START_SETTING], dtype=torch.float64), theta))
    assert g0 < float(g_rand.min()) and g0 < g_start
    assert prior.f_x0 == pytest.approx(-g0, rel=1e-6)
    assert prior.f_inf < prior.f_x0
    assert prior.noise == PRIOR_NOISE_FLOOR_UM
    P = prior.precision
    assert torch.allclose(P, P.T)
    assert float(torch.linalg.eigvalsh(P).min()) > 0
    assert ares_prior(target, 0.0) is prior  # cached


@pytest.mark.slow
def test_bench_ares_pigp_lowers_the_mae(tmp_path, capsys):
    """`pigp bench ares --methods pigp --trial-ids 3 --steps 12` runs and ends below the start's
    MAE (noise-free beam)."""
    args = ["--methods", "pigp", "--trial-ids", str(TRIAL), "--steps", "12", "--quiet"]
    rc = main(["bench", "ares", *args, "-o", str(tmp_path)])
    assert rc == 0
    steps = pd.read_csv(tmp_path / "steps.csv")
    assert list(steps["method"].unique()) == ["pigp"]
    start = steps.loc[steps["step"] == 0, "mae_true"].iloc[0]
    final = steps.loc[steps["step"] == 12, "mae_true"].iloc[0]
    assert final < start
    assert "pigp" in capsys.readouterr().out
