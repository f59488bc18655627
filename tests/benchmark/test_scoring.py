"""Tests of the benchmark scores on hand-made tables with closed-form answers."""

import math

import numpy as np
import pandas as pd
import pytest

from pigp_torch.bench import first_moves, run_scores, summarize


def _run(method, seed, f_true, f0=0.5, f_star=1.5):
    f = np.asarray(f_true, dtype=float)
    best = np.maximum.accumulate(f)
    return pd.DataFrame(
        {
            "method": method,
            "machine_seed": seed,
            "step": np.arange(f.size),
            "f_true": f,
            "f0": f0,
            "f_star": f_star,
            "gain_fraction": (best - f0) / (f_star - f0),
        }
    )


@pytest.fixture
def table():
    # target f0 + 0.95 (f* - f0) = 1.45: run 1 reaches it at step 3 (evaluation 4), run 2 never
    return pd.concat(
        [
            _run("a", 1, [0.5, 0.9, 1.2, 1.46, 1.44]),
            _run("a", 2, [0.5, 0.6, 0.55, 0.7, 1.0]),
            _run("b", 1, [0.5, 1.5, 0.4]),
        ],
        ignore_index=True,
    )


def test_steps_to_95_first_hit_and_unreached_is_budget_plus_one(table):
    """Steps-to-95 % = 1-based evaluation of the first hit; an unreached run scores budget+1."""
    s = run_scores(table, at=(2, 4)).set_index(["method", "machine_seed"])
    assert s.loc[("a", 1), "steps_to_95"] == 4.0
    assert s.loc[("a", 2), "steps_to_95"] == 6.0
    assert s.loc[("b", 1), "steps_to_95"] == 2.0
    assert s["reached_95"].tolist() == [True, False, True]
    assert s.loc[("a", 1), "best_f_true"] == 1.46


def test_gain_after_n_evaluations_uses_best_so_far(table):
    """Gain after n evaluations = (max f_true of the first n - f0) / (f* - f0); NaN if short."""
    s = run_scores(table, at=(2, 4)).set_index(["method", "machine_seed"])
    assert s.loc[("a", 1), "gain_2"] == pytest.approx(0.4)
    assert s.loc[("a", 1), "gain_4"] == pytest.approx(0.96)
    assert s.loc[("a", 2), "gain_4"] == pytest.approx(0.2)
    assert s.loc[("b", 1), "gain_2"] == pytest.approx(1.0)
    assert math.isnan(s.loc[("b", 1), "gain_4"])


def test_summary_median_and_iqr(table):
    """The summary gives median and linear-interpolated quartiles per method and run counts."""
    out = summarize(table, at=(2, 4))
    a = out.loc["a"]
    assert (a["n_runs"], a["n_reached_95"], a["budget"]) == (2, 1, 5)
    assert (a["steps_to_95_median"], a["steps_to_95_q25"], a["steps_to_95_q75"]) == (5, 4.5, 5.5)
    assert a["gain_4_median"] == pytest.approx(0.58)
    assert out.loc["b", "gain_2_median"] == pytest.approx(1.0)
    assert math.isnan(out.loc["b", "gain_4_median"])
    assert list(out.index) == ["a", "b"]


def test_other_fraction_and_bad_inputs(table):
    """fraction=0.5 moves the target to f0 + 0.5 (f* - f0); bad fraction or columns raise."""
    s = run_scores(table, fraction=0.5, at=())
    assert s["steps_to_50"].tolist() == [3.0, 5.0, 2.0]
    with pytest.raises(ValueError, match="fraction"):
        run_scores(table, fraction=1.5)
    with pytest.raises(ValueError, match="lacks columns"):
        summarize(table.drop(columns="f_star"))


def test_steps_within_uses_the_larger_of_five_percent_and_the_noise(table):
    """Steps-to-within: f >= f* - max(0.05 (f* - f0), sigma_n); with sigma_n = 0.2 the bar
    drops from 1.45 to 1.3, so run 'a' 1 counts at evaluation 4 and, with 0.6, at 3."""
    s = run_scores(table, at=(), noise=0.04).set_index(["method", "machine_seed"])
    assert s.loc[("a", 1), "steps_within"] == 4.0  # bar 1.45
    assert s.loc[("a", 2), "steps_within"] == 6.0  # never
    s = run_scores(table, at=(), noise=0.3).set_index(["method", "machine_seed"])
    assert s.loc[("a", 1), "steps_within"] == 3.0  # bar 1.2
    assert s.loc[("a", 2), "steps_within"] == 6.0  # 1.0 < 1.2


def test_summary_reports_the_compute_per_ask(table):
    """Median and 90th percentile of ask_time_s per method, the start point left out."""
    t = table.copy()
    t["ask_time_s"] = np.where(t["step"] == 0, 100.0, t["step"] * 0.1)
    out = summarize(t, at=())
    assert out.loc["b", "ask_time_s_median"] == pytest.approx(0.15)
    assert out.loc["a", "ask_time_s_median"] == pytest.approx(0.25)
    assert out.loc["a", "ask_time_s_p90"] == pytest.approx(0.4)


def test_first_moves_counts_each_run_once_at_its_first_notice():
    """Two notices in one run count once, at the first (evaluation = step + 1); a run without
    notices, or a table without a notice column, has no entry."""
    a = _run("pigp-physics", 1, [0.5, 0.6, 0.7, 0.8, 0.9])
    b = _run("pigp-physics", 2, [0.5, 0.6, 0.7, 0.8, 0.9])
    c = _run("ml2", 1, [0.5, 0.6, 0.7])
    a["notice"], b["notice"], c["notice"] = None, None, None
    a.loc[a["step"] == 3, "notice"] = "prior_rejected"
    a.loc[a["step"] == 1, "notice"] = "prior_rejected"
    b.loc[b["step"] == 2, "notice"] = "safety_stop"
    first = first_moves(pd.concat([a, b, c], ignore_index=True))
    assert first.to_dict() == {("pigp-physics", 1): 2}
    assert first_moves(c.drop(columns="notice")).empty
    # a CSV whose runs wrote no notice reads the column back as float NaN
    assert first_moves(c.assign(notice=float("nan"))).empty
