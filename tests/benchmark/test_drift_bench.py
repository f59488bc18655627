"""benchmarks/drift_bench.py: held-out sets and unknown families are refused before any run; a
short direct-method run prints the scores and writes the per-reading series."""

from __future__ import annotations

import pandas as pd
import pytest

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
    assert list(table.columns) == ["method", "id", "reading", "mae_true_um"]
    assert len(table) == 13  # 12 readings + the set-back
    mae = table["mae_true_um"].to_numpy()
    text = capsys.readouterr().out
    assert f"best {mae[:-1].min():8.1f} um" in text
    assert f"final {mae[-1]:8.1f} um" in text
