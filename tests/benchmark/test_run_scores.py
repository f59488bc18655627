"""benchmarks/run_scores.py: one row per run, with the case, compute per ask and the prior check."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from tests.benchmark.conftest import load_script
from tests.benchmark.test_scoring import _run


@pytest.fixture(scope="module")
def script():
    return load_script("run_scores")


def _with(run, ask_ms, notice_at=None):
    run = run.assign(ask_time_s=np.asarray(ask_ms, dtype=float) / 1e3, notice=None)
    if notice_at is not None:
        run.loc[run["step"] == notice_at, "notice"] = "prior_rejected"
    return run


def test_scores_per_case_and_run(script, tmp_path):
    # run 1 reaches 1.45 = f0 + 0.95 (f* - f0) at evaluation 4; run 2 never (budget 5 + 1)
    a = _with(_run("a", 1, [0.5, 0.9, 1.2, 1.46, 1.44]), [0, 10, 30, 20, 40], notice_at=2)
    b = _with(_run("a", 2, [0.5, 0.6, 0.55, 0.7, 1.0]), [0, 5, 5, 7, 9])
    raw = pd.concat([a.assign(case="scale×10"), b.assign(case="scale×10")], ignore_index=True)
    path = tmp_path / "raw.csv"
    raw.to_csv(path, index=False)
    out = tmp_path / "scores.csv"
    assert script.main([str(path), "-o", str(out)]) == 0
    s = pd.read_csv(out)
    assert list(s["case"]) == ["scale×10", "scale×10"]
    assert list(s["steps_to_95"]) == [4, 6]
    assert list(s["reached_95"]) == [True, False]
    # the median ask excludes the start point (evaluation 1): (20 + 30) / 2 and (5 + 7) / 2
    assert s["ask_ms_median"].tolist() == pytest.approx([25.0, 6.0])
    assert s["prior_rejected_at"].iloc[0] == 3 and np.isnan(s["prior_rejected_at"].iloc[1])


def test_a_run_table_without_cases_is_the_control(script):
    s = script.scores_of(_with(_run("b", 1, [0.5, 1.5, 0.4]), [0, 1, 2]))
    assert list(s["case"]) == ["control"] and int(s["steps_to_95"].iloc[0]) == 2
    assert s["gain_20"].isna().all()  # the run is shorter than 20 evaluations


def test_the_mismatch_table_counts_runs_that_moved_not_notices():
    """A run whose prior check moves twice (stage 1, then stage 2) is one run that moved on,
    at its first move."""
    table = load_script("mismatch").table
    a = _with(_run("pigp-physics", 1, [0.5, 0.9, 1.2, 1.46, 1.44]), [0, 1, 1, 1, 1], notice_at=1)
    a.loc[a["step"] == 3, "notice"] = "prior_rejected"  # the second move of the same run
    b = _with(_run("pigp-physics", 2, [0.5, 0.6, 0.55, 0.7, 1.0]), [0, 1, 1, 1, 1], notice_at=3)
    c = _with(_run("pigp-physics", 3, [0.5, 0.6, 0.55, 0.7, 1.0]), [0, 1, 1, 1, 1])
    row = table(pd.concat([a, b, c], ignore_index=True).assign(case="rot45")).iloc[0]
    assert row["rejected"] == "2/3"
    assert row["rejected_at"] == 3.0  # evaluations 2 (run 1's first move) and 4 (run 2's)


def test_the_mismatch_table_takes_the_baselines_from_kept_scores(script, tmp_path, capsys):
    """The suite's rules compare pigp-physics with baselines whose runs are kept only as
    per-run scores: those scores decide the rules, and their other methods are ignored."""
    up = np.minimum(np.linspace(0.5, 1.5, 100), 1.5)  # gain after 40: 0.39, after 100: 1.0
    slow = np.linspace(0.5, 0.9, 100)  # gain after 40 0.16, after 100 0.40
    physics = pd.concat([_run("pigp-physics", s, up) for s in (1, 2)], ignore_index=True)
    mm = tmp_path / "mm.csv"
    physics.assign(case="scale×3").to_csv(mm, index=False)
    control = tmp_path / "control.csv"
    physics.to_csv(control, index=False)
    baselines = pd.concat(
        [_run("ml2", s, up) for s in (1, 2)]  # as good as pigp-physics: rule 100 holds (≥)
        + [_run("xopt-ucb", s, slow) for s in (1, 2)]
        + [_run("ml2", 3, slow)],  # another machine: not in the suite, left out
        ignore_index=True,
    ).assign(ask_time_s=0.01, notice=None)
    raw = tmp_path / "baselines.csv"
    baselines.to_csv(raw, index=False)
    kept = tmp_path / "scores.csv"
    assert script.main([str(raw), "-o", str(kept)]) == 0
    extra = pd.read_csv(kept).assign(method="pigp-physics", gain_40=0.0)  # ignored
    pd.concat([pd.read_csv(kept), extra]).to_csv(kept, index=False)
    table = load_script("mismatch_table")
    assert table.main([str(mm), "--control", str(control), "--baseline-scores", str(kept)]) == 0
    rows = {r.split("|")[1].strip(): r for r in capsys.readouterr().out.splitlines() if "|" in r}
    for case in ("control", "scale×3"):
        cells = [c.strip() for c in rows[case].split("|")[1:-1]]
        assert cells[1].startswith("0.39") and cells[2].startswith("1.00")
        assert cells[3] == "0.39 / 1.00" and cells[4] == "0.16 / 0.40"
        assert cells[5] == "yes" and cells[6] == "yes"
    slower = tmp_path / "slower.csv"
    pd.concat([_run("pigp-physics", s, slow) for s in (1, 2)]).assign(case="rot45").to_csv(
        slower, index=False
    )
    assert table.main([str(slower), "--control", str(control), "--baseline-scores", str(kept)]) == 0
    row = next(r for r in capsys.readouterr().out.splitlines() if r.startswith("| rot45"))
    assert [c.strip() for c in row.split("|")[1:-1]][5:7] == ["**no**", "**no**"]


def test_scores_keep_runs_of_two_families_apart(script):
    """Machine 1 of the project and of the wide family are two runs, each scored on its own."""
    a = _with(_run("a", 1, [0.5, 1.5, 0.4]), [0, 1, 2]).assign(family="project")
    b = _with(_run("a", 1, [0.5, 0.6, 0.7]), [0, 1, 2]).assign(family="wide")
    s = script.scores_of(pd.concat([a, b], ignore_index=True))
    assert list(s["family"]) == ["project", "wide"]
    assert list(s["steps_to_95"]) == [2, 4] and list(s["reached_95"]) == [True, False]


def test_the_summary_table_reports_both_families(tmp_path, capsys):
    """table_summary labels wide-family runs ``method [wide]`` and takes each run's n95 from its
    own family."""
    summary = load_script("table_summary")
    a = _with(_run("a", 1, [0.5, 1.5, 0.4]), [0, 1, 2]).assign(family="project", budget=3)
    b = _with(_run("a", 1, [0.5, 0.6, 1.46]), [0, 1, 2]).assign(family="wide", budget=3)
    path = tmp_path / "runs.csv"
    pd.concat([a, b], ignore_index=True).to_csv(path, index=False)
    n95 = tmp_path / "n95.csv"
    pd.DataFrame({"family": ["project", "wide"], "machine_seed": [1, 1], "n95": [4, 2]}).to_csv(
        n95, index=False
    )
    assert summary.main([str(path), "--n95", str(n95)]) == 0
    out = capsys.readouterr().out
    # steps to 95 %: 2 (project) and 3 (wide); ratios to n95: 2 / 4 and 3 / 2
    assert "| `a` | 3 | 1/1 | 2.0 (2.0–2.0) | 0.50 (0.50–0.50) |" in out
    assert "| `a [wide]` | 3 | 1/1 | 3.0 (3.0–3.0) | 1.50 (1.50–1.50) |" in out
