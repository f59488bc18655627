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


@pytest.mark.slow  # two 12-reading ARES tracker runs: ~1-3 min on a loaded host
def test_an_ares_track_run_records_the_tracked_beam_beside_the_drifting_truth(figure):
    """A 12-reading ``ares-physics`` run on tuning trial 0 of the drift family: its true MAE per
    reading is drift_bench's run of the same trial; the true centroid at the fixed setting
    moves with the incoming beam (the family drifts); the tracked model's prediction there is
    recorded for every reading, in µm, and after the fit it is within 200 µm of the truth."""
    track = figure.ares_track_run(0, "drift", 12)
    for name in ("mu_x", "mu_y"):
        truth = track[track.name == f"true_{name}"].sort_values("reading")
        model = track[track.name == f"model_{name}"].sort_values("reading")
        assert truth.reading.tolist() == model.reading.tolist() == list(range(12))
        assert set(truth.unit) == set(model.unit) == {"µm"}
        assert truth.value.iloc[-1] != truth.value.iloc[0]
        assert abs(model.value.iloc[-1] - truth.value.iloc[-1]) < 200.0
    mae = track[track.name == "mae_true"].value.tolist()
    bench = load_script("drift_bench").ares_run((0, "ares-physics", "drift", 101, 12, 0.0,
                                                 (6, 12), None))  # fmt: skip
    assert mae == pytest.approx(bench["series"][:12].tolist(), rel=1e-12)  # drift_bench's run


def test_a_held_out_ares_trial_is_refused(figure, tmp_path, capsys):
    """--track on an ARES report trial (50-149, or any 50+) exits 2 with one line."""
    csv = _table(tmp_path / "ares.csv", column="mae_true_um")
    out = tmp_path / "fig.png"
    assert figure.main(["ares", "--csv", csv, "--track", "60", "-o", str(out)]) == 2
    assert "held out" in capsys.readouterr().err and not out.exists()


@pytest.mark.slow  # builds the drifting ring and its fast model: ~2.5 min on a loaded host
def test_a_spear3_track_run_records_the_fit_beside_the_moving_truth(figure):
    """A 12-reading ``pigp-physics`` run on tuning machine 101 of the drift family (the saved
    exact-model prior): the true peak of every reading (mA/min, positive), the fitted peak and
    the memory recorded per reading."""
    from pathlib import Path

    prior = Path(__file__).parents[2] / "docs" / "data" / "prior_spear3_seed0_exact.json"
    track = figure.track_run(101, "drift", 12, str(prior))
    truth = track[track.name == "true_peak"]
    assert truth.reading.tolist() == list(range(12)) and (truth.value > 0).all()
    assert set(truth.unit) == {"mA/min"}
    assert {"peak", "remembered"} <= set(track.name)
