"""benchmarks/drift_bench.py: held-out sets and unknown families are refused before any run; a
short direct-method run prints the scores and writes the per-reading series; the summary table
and the final reading at the optimizer's recommendation."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import torch

from tests.benchmark.conftest import load_script


@pytest.fixture(scope="module")
def bench():
    return load_script("drift_bench")


@pytest.mark.parametrize(
    "argv",
    [
        ["ares", "--trials", "48-52", "--methods", "nelder-mead"],
        ["spear3", "--seeds", "24", "--methods", "nelder-mead"],
    ],
)
def test_held_out_sets_are_refused(bench, argv):
    with pytest.raises(SystemExit, match="held out"):
        bench.main(argv)


def test_unknown_family_exits_2(bench, capsys):
    assert bench.main(["ares", "--family", "nope", "--methods", "nelder-mead"]) == 2
    assert "unknown family 'nope'" in capsys.readouterr().err


def test_short_ares_run_scores_the_true_beam(bench, tmp_path, capsys):
    out = tmp_path / "steps.csv"
    argv = ["ares", "--family", "laser-step", "--trials", "0", "--methods", "nelder-mead",
            "--readings", "12", "--window", "4", "12", "--csv", str(out)]  # fmt: skip
    assert bench.main(argv) == 0
    table = pd.read_csv(out)
    assert list(table.columns) == ["method", "id", "reading", "mae_true_um", "mae_read_um"]
    assert len(table) == 13  # 12 readings + the set-back
    mae = table["mae_true_um"].to_numpy()
    text = capsys.readouterr().out
    assert f"best {mae[:-1].min():8.1f} um" in text
    assert f"final {mae[-1]:8.1f} um" in text
    # a noise-free screen reads the true beam: the luckiest reading is the best one
    assert table["mae_read_um"].to_numpy() == pytest.approx(mae, rel=1e-12)
    assert f"lucky {mae[:-1].min():.3f} um" in text


def test_the_lucky_mae_is_the_true_mae_where_the_read_mae_was_lowest(bench, tmp_path, capsys):
    """A jittering screen: the reads differ from the true beam, and the lucky MAE is the true
    MAE of the reading (before the set-back) whose read MAE is the lowest -- printed, and in the
    summary table rebuilt from the CSV."""
    out = tmp_path / "jitter.csv"
    argv = ["ares", "--family", "screen-jitter", "--trials", "1", "--methods", "nelder-mead",
            "--readings", "15", "--window", "5", "15", "--csv", str(out), "--summary"]  # fmt: skip
    assert bench.main(argv) == 0
    text = capsys.readouterr().out
    table = pd.read_csv(out)
    true, read = table["mae_true_um"].to_numpy(), table["mae_read_um"].to_numpy()
    assert np.abs(true - read).max() > 0.1  # µm: the screen's noise
    expected = true[:-1][np.argmin(read[:-1])]
    assert f"lucky {expected:.3f} um" in text
    rows = text[text.index("| method |") :].strip().splitlines()
    cell = f"| {expected:.1f} ({expected:.1f}–{expected:.1f}) |"  # one trial: no spread
    assert rows[0].endswith("| lucky MAE (µm) |") and rows[2].endswith(cell)
    assert bench.main(["ares", "--window", "5", "15", "--from-csv", str(out)]) == 0
    assert capsys.readouterr().out.strip().splitlines() == rows


def test_summary_table_is_the_median_and_iqr_over_trials_and_rebuilds_from_csv(
    bench, tmp_path, capsys
):
    out = tmp_path / "steps.csv"
    argv = ["ares", "--family", "drift", "--trials", "0-2", "--readings", "14", "--window", "4",
            "14", "--methods", "nelder-mead", "nelder-mead-restart", "--csv", str(out),
            "--summary"]  # fmt: skip
    assert bench.main(argv) == 0
    printed = capsys.readouterr().out
    table = pd.read_csv(out)
    rows = printed[printed.index("| method |") :].strip().splitlines()
    assert rows[0].startswith("| method | trials | median true MAE over window (µm) |")
    assert [r.split(" | ")[0] for r in rows[2:]] == ["| nelder-mead", "| nelder-mead-restart"]
    nm = table[table["method"] == "nelder-mead"]
    finals = nm.groupby("id")["mae_true_um"].last().to_numpy()
    q1, med, q3 = np.percentile(finals, [25, 50, 75])
    assert f"| {med:.1f} ({q1:.1f}–{q3:.1f}) |" in rows[2]
    assert bench.main(["ares", "--window", "4", "14", "--from-csv", str(out)]) == 0
    assert capsys.readouterr().out.strip().splitlines() == rows


def test_the_final_reading_is_at_nelder_mead_restarts_recommendation():
    from pigp_torch.machines import KINDS
    from pigp_torch.machines.drift import drive
    from pigp_torch.optimizers.nm_restart import NelderMeadRestart

    machine = KINDS["ares-ea"].drift_machine(family="drift", seed=101, trial=0, noise=0.0)
    opt = NelderMeadRestart(machine.bounds, period=8, maximize=machine.maximize)
    X, true = drive(machine, opt, 20)
    assert [n for n, _, _ in opt.restarts] == [8, 16]
    assert torch.equal(X[-1], opt.restarts[-1][1]) and len(X) == 21
    assert torch.equal(true[-1], machine.last_true_observables)


def test_spear3_runs_get_the_methods_options(bench, monkeypatch):
    """--options reaches a SPEAR3 run's method (``spec.with_options``) before any ring is
    built, as for ARES."""
    seen = {}

    class Stop(Exception):
        pass

    class Spec:
        needs_prior = False

        def with_options(self, **options):
            seen.update(options)
            raise Stop

    monkeypatch.setitem(bench.METHODS, "probe-method", Spec())
    with pytest.raises(Stop):
        bench.main(["spear3", "--seeds", "101", "--methods", "probe-method",
                    "--options", '{"forgetting": {"slopes": [0]}}'])  # fmt: skip
    assert seen == {"forgetting": {"slopes": [0]}}
