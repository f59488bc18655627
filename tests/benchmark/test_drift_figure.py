"""benchmarks/drift_figure.py: the figure of a drifting machine from drift_bench tables."""

from __future__ import annotations

import pandas as pd
import pytest

from tests.benchmark.conftest import load_script


@pytest.fixture(scope="module")
def figure():
    return load_script("drift_figure")


def _table(path, column="gain"):
    rows = [(m, i, t, 0.5 + 0.1 * i + 0.001 * t) for m in ("a", "b") for i in (1, 2)
            for t in range(30)]  # fmt: skip
    pd.DataFrame(rows, columns=["method", "id", "reading", column]).to_csv(path, index=False)
    return str(path)


def test_a_figure_of_the_tables_with_the_tracked_unknowns_is_written(figure, tmp_path):
    """Two methods x two machines of gain, and a saved --track table (reused, not rerun): the
    PNG is written (rows: the gain, then peak, travel and memory) and the command exits 0."""
    csv = _table(tmp_path / "ring.csv")
    track = pd.DataFrame(
        [(t, name, 1.0 + t, unit) for t in range(30) for name, unit in
         (("peak", "mA/min"), ("true_peak", "mA/min"), ("optimum_moved", "A"),
          ("true_optimum_moved", "A"), ("remembered", "readings"))],
        columns=["reading", "name", "value", "unit"],
    )  # fmt: skip
    track.to_csv(tmp_path / "track.csv", index=False)
    out = tmp_path / "fig.png"
    argv = ["spear3", "--csv", csv, "--track", "101", "--track-csv", str(tmp_path / "track.csv")]
    assert figure.main([*argv, "-o", str(out)]) == 0
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and out.stat().st_size > 10_000


def test_held_out_machines_and_the_wrong_column_are_refused(figure, tmp_path, capsys):
    """--track on a report machine (1-24) and an ARES figure of gain tables exit 2 with one
    line each; nothing is written."""
    csv = _table(tmp_path / "ring.csv")
    out = tmp_path / "fig.png"
    assert figure.main(["spear3", "--csv", csv, "--track", "5", "-o", str(out)]) == 2
    assert "held out" in capsys.readouterr().err
    assert figure.main(["ares", "--csv", csv, "-o", str(out)]) == 2
    assert "mae_true_um" in capsys.readouterr().err
    assert not out.exists()
