"""What a person reads carries the unit they read: a beam in µm (the log keeps m), each knob
with its own unit, and one knob panel per unit in the report figure."""

from __future__ import annotations

import io
from pathlib import Path

import torch

from pigp_torch._utils.units import display_unit
from pigp_torch.loop.progress import ProgressLine
from pigp_torch.reporting.figures import draw_run, in_display_units

ARES = ["AREAMQZM1", "AREAMQZM2", "AREAMCVM1", "AREAMQZM3", "AREAMCHM1"]
ARES_UNITS = ["1/m^2", "1/m^2", "rad", "1/m^2", "rad"]


def test_a_length_in_m_reads_in_um_and_other_units_as_they_are():
    assert display_unit("m") == (1e6, "µm")
    assert display_unit("mA/min") == (1.0, "mA/min") and display_unit(None) == (1.0, "")


def test_the_progress_line_shows_a_beam_in_um_and_each_knob_move_in_its_unit():
    out = io.StringIO()
    line = ProgressLine(5, ARES, maximize=False, unit=ARES_UNITS, objective_unit="m", out=out,
                        clock=lambda: 0.0)  # fmt: skip
    line({"step": 0, **dict.fromkeys(ARES, 0.0), "y": 8.23381e-07})
    line({"step": 1, **dict.fromkeys(ARES, 0.0), "AREAMCHM1": 0.002, "y": 9.0e-07})
    first, second = out.getvalue().splitlines()
    assert "y = 0.823381 µm  best = 0.823381 µm" in first
    assert "y = 0.9 µm  best = 0.823381 µm  move 0.002 rad (AREAMCHM1)" in second


def _ares_data() -> dict:
    n = 4
    X = torch.tensor([[10.0, -10.0, 0.0, 10.0, 0.0]] * n, dtype=torch.float64)
    X[:, 2] = torch.linspace(0, 0.003, n, dtype=torch.float64)
    return {
        "path": Path("run.jsonl"), "method": "ares-physics", "knob_names": ARES,
        "unit": "1/m^2 or rad", "knob_units": ARES_UNITS, "objective_unit": "m",
        "optimum": None, "maximize": False, "X": X, "noise": 2e-6, "fit": None,
        "Y": torch.tensor([5e-4, 1e-4, 2e-6, 1e-6], dtype=torch.float64),
        "true": torch.tensor([5e-4, 1e-4, 2e-6, 1e-6], dtype=torch.float64),
        "bounds": torch.tensor([[-72, -72, -0.0062, -72, -0.0062], [72, 72, 0.0062, 72, 0.0062]],
                               dtype=torch.float64),
        "notices": [], "budget": n, "status": "completed",
        "observables": torch.tensor([[1e-5, 2e-5, 3e-5, 4e-5]] * n, dtype=torch.float64),
        "observable_names": ["mu_x", "sigma_x", "mu_y", "sigma_y"],
        "observable_units": ["m"] * 4,
    }  # fmt: skip


def test_the_report_data_in_display_units_scales_readings_and_beam_only():
    data = _ares_data()
    shown = in_display_units(data)
    assert shown["objective_unit"] == "µm" and shown["observable_units"] == ["µm"] * 4
    assert torch.allclose(shown["Y"], 1e6 * data["Y"]) and shown["noise"] == 2.0
    assert torch.allclose(shown["observables"][0], torch.tensor([10.0, 20, 30, 40]).double())
    assert shown["X"] is data["X"] and data["objective_unit"] == "m"  # knobs, input unchanged


def test_quadrupoles_and_correctors_get_a_knob_panel_each():
    import matplotlib.pyplot as plt

    fig, axes = draw_run(_ares_data())
    try:
        assert len(axes) == 3
        assert axes[0].get_ylabel() == "objective (µm)"
        assert axes[1].get_ylabel() == "knob setting (1/m^2)"
        assert axes[2].get_ylabel() == "knob setting (rad)"
        assert [t.get_text() for t in axes[2].get_legend().get_texts()] == ["AREAMCVM1",
                                                                           "AREAMCHM1"]  # fmt: skip
        assert axes[2].get_ylim()[1] < 0.01  # the correctors on their own scale, not k1's
        assert max(axes[0].get_lines()[0].get_ydata()) == 500.0  # 5e-4 m read as 500 µm
    finally:
        plt.close(fig)


def test_a_runs_table_carries_units_in_its_headers_and_reads_back_with_plain_names(tmp_path):
    import pandas as pd

    from pigp_torch.data.tables import read_table, with_units

    df = pd.DataFrame({"step": [0, 1], "machine_seed": [1, 1], "01G-QSS4": [0.0, 2.5],
                       "y": [0.6, 0.7], "method": ["pigp"] * 2, "ask_time_s": [0.1, 0.2],
                       "gain_fraction": [0.0, 0.5], "steps_to_95_median": [3.0, 3.0]})  # fmt: skip
    with_units(df, {"01G-QSS4": "A"}).to_csv(tmp_path / "runs.csv", index=False)
    header = (tmp_path / "runs.csv").read_text().splitlines()[0]
    assert header == ("step,machine_seed,01G-QSS4 [A],y [mA/min],method,ask_time_s,"
                      "gain_fraction,steps_to_95_median [evaluations]")  # fmt: skip
    pd.testing.assert_frame_equal(read_table(tmp_path / "runs.csv"), df)
    df.to_csv(tmp_path / "old.csv", index=False)  # a file written before the units
    pd.testing.assert_frame_equal(read_table(tmp_path / "old.csv"), df)
