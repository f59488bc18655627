"""benchmarks/paired_screen.py: paired differences against the baseline with standard errors."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from tests.benchmark.conftest import load_script
from tests.benchmark.test_scoring import _run


def _reaching(method, seed, at, ask_ms, n=40):
    """A run at f0 = 0.5 that jumps to 1.46 (over 95 % of f* - f0 = 1) at evaluation ``at``."""
    f = np.where(np.arange(n) + 1 >= at, 1.46, 0.5)
    return _run(method, seed, f).assign(ask_time_s=ask_ms / 1e3)


def test_paired_differences_and_their_standard_errors(tmp_path, capsys):
    script = load_script("paired_screen")
    base = [_reaching("default", s, at, 100.0) for s, at in ((1, 10), (2, 20), (3, 99))]
    new = [_reaching("v", s, at, 150.0) for s, at in ((1, 8), (2, 14), (3, 30), (4, 5))]
    df = pd.concat(base + new, ignore_index=True)
    t = script.paired_table(df, "default")
    assert t.loc["v", "machines"] == 3  # seed 4 has no baseline run
    assert t.loc["v", "reached_95"] == 3 and t.loc["default", "reached_95"] == 2
    diff = np.array([8 - 10, 14 - 20, 30 - 41])  # never reached: one past the budget of 40
    assert t.loc["v", "d_steps"] == pytest.approx(diff.mean())
    assert t.loc["v", "se_steps"] == pytest.approx(diff.std(ddof=1) / math.sqrt(3))
    assert t.loc["v", "steps_median"] == 14.0 and t.loc["default", "steps_median"] == 20.0
    # gain after 20: 0.96 for both on seeds 1-2, 0 on seed 3 (v reaches at 30): no difference
    assert t.loc["v", "d_gain_20"] == pytest.approx(0.0) and t.loc["v", "se_gain_20"] == 0.0
    assert t.loc["v", "d_gain_40"] == pytest.approx(0.96 / 3)
    assert t.loc["v", "ask_ratio"] == pytest.approx(1.5)
    path = tmp_path / "runs.csv"
    df.to_csv(path, index=False)
    assert script.main([str(path)]) == 0
    assert "d_steps" in capsys.readouterr().out
    with pytest.raises(ValueError, match="baseline 'x' is not among"):
        script.paired_table(df, "x")


def test_kept_per_run_scores_join_new_runs(tmp_path, capsys):
    """A per-run scores file (benchmarks/run_scores.py) joins traces: the same differences as
    from the traces alone; --family picks the rows; a run twice on one machine is refused."""
    script, scores = load_script("paired_screen"), load_script("run_scores")
    base = [_reaching("default", s, at, 100.0) for s, at in ((1, 10), (2, 20), (3, 99))]
    new = [_reaching("v", s, at, 150.0) for s, at in ((1, 8), (2, 14), (3, 30))]
    df = pd.concat(base + new, ignore_index=True)
    whole = script.paired_table(df, "default")
    kept = scores.scores_of(df[df["machine_seed"] < 3])
    other = kept.assign(family="wide", method=kept["method"] + "_wide")  # not picked
    pd.concat([kept, other]).to_csv(tmp_path / "kept.csv", index=False)
    df[df["machine_seed"] == 3].to_csv(tmp_path / "new.csv", index=False)
    assert script.main([str(tmp_path / "kept.csv"), str(tmp_path / "new.csv")]) == 0
    out = capsys.readouterr().out
    assert "_wide" not in out
    row = next(line for line in out.splitlines() if line.startswith("v "))
    d_steps, se_steps = (float(v) for v in row.split()[5:7])  # after the medians
    assert d_steps == pytest.approx(whole.loc["v", "d_steps"], abs=1e-3)
    assert se_steps == pytest.approx(whole.loc["v", "se_steps"], abs=1e-3)
    assert float(row.split()[-1]) == pytest.approx(1.5)  # 150 / 100 ms on each machine
    df.to_csv(tmp_path / "all.csv", index=False)
    with pytest.raises(SystemExit, match="ran twice"):
        script.main([str(tmp_path / "kept.csv"), str(tmp_path / "all.csv")])
