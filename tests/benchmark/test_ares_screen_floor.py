"""benchmarks/ares_screen_floor.py: the resolution floor of a noisy-screen run's final."""

from __future__ import annotations

import math

import pandas as pd
import pytest

from tests.benchmark.conftest import load_script

pytest.importorskip("cheetah")


def test_the_floor_is_the_true_mae_of_a_beam_read_on_the_target():
    """A beam whose read sizes sqrt(sigma^2 + r^2) equal the target t has sigma = sqrt(t^2 - r^2):
    its MAE is sum (t - sigma) / 4 over the two sizes (the centroids read true), and a target
    size at or below r is missed by all of itself."""
    script = load_script("ares_screen_floor")
    t = [1e-4, 30e-6, -2e-4, 40e-6]
    r = 15e-6
    expected = (30 - math.sqrt(30**2 - 15**2) + 40 - math.sqrt(40**2 - 15**2)) / 4
    assert script.floor_um(t, r) == pytest.approx(expected, rel=1e-12)
    assert script.floor_um([0, 10e-6, 0, 40e-6], r) == pytest.approx(
        (10 + 40 - math.sqrt(40**2 - 15**2)) / 4, rel=1e-12
    )
    assert script.floor_um(t, 0.0) == 0.0


def test_the_table_of_a_run_csv(tmp_path, capsys):
    """Per trial: the floor from the machine's target and resolution, the final (the last row)
    and the best (the other rows) of the CSV, and the medians."""
    from pigp_torch.machines import KINDS

    rows = [("ares-physics", 50, k, v) for k, v in enumerate([900.0, 2.0, 0.5, 1.0])]
    path = tmp_path / "runs_screen-jitter_x.csv"
    pd.DataFrame(rows, columns=["method", "id", "reading", "mae_true_um"]).to_csv(path, index=False)
    script = load_script("ares_screen_floor")
    assert script.main([str(path), "--repeats", "3"]) == 0
    out = capsys.readouterr().out
    m = KINDS["ares-ea"].drift_machine(family="screen-jitter", seed=101, trial=50, objective="mae")
    floor = script.floor_um(m.target, 15e-6)
    line = next(s for s in out.splitlines() if s.strip().startswith("50 "))
    assert line.split()[1:6] == [f"{floor:.2f}", "1.00", "0.50", "2.00", f"{floor / 0.5:.2f}"]
    assert "median final/best 2.00" in out
