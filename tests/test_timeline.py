"""A run against wall-clock time: the readings' times and the tracked unknowns from the run log,
in the report (a second figure on its page) and in the dashboard (its state and, in headless
Chromium, the plots with their units)."""

from __future__ import annotations

import shutil
import subprocess

import matplotlib.pyplot as plt
import pytest

from pigp_torch.data.runlog import RunLog, read_log
from pigp_torch.reporting.dashboard import run_state, write_final_page
from pigp_torch.reporting.report import run_report, write_report
from pigp_torch.reporting.timeline import draw_time, time_unit, timeline, unit_groups

KNOBS = ["01G-QSS4", "02G-QSS3"]
BROWSER = shutil.which("chromium") or shutil.which("chromium-browser")
T0 = 1.7e9  # s since the epoch


def track_log(path, n=6, dt=600.0):
    """A track-style log: a reading every ``dt`` s; tracked beam_x (m) and a gain (1) from the
    second reading on; the last record without ``t_read`` (an older writer's)."""
    with RunLog.create(path, {"knob_names": KNOBS, "method": "fake", "maximize": True}) as log:
        log.log_start([0.0, 0.0], budget=100, first_step=0)
        for k in range(n):
            tracked = {} if k == 0 else {"beam_x": [1e-6 * k, "m"], "gain": [0.5 + k, "1"]}
            fields = {"t_set": T0 + dt * k - 1, "t_read": T0 + dt * k} if k < n - 1 else {}
            log.log_evaluation(k, [0.1 * k, 0.0], 1.0 + 0.01 * k, tracked=tracked, **fields)
        log.log_end("completed", "the time limit passed", restored_to="estimate")
    return path


@pytest.mark.parametrize(("span", "unit"), [(0.0, "s"), (120.0, "s"), (121.0, "min"),
                                            (7200.0, "min"), (8 * 3600.0, "h")])  # fmt: skip
def test_the_time_axis_unit_follows_the_runs_length(span, unit):
    assert time_unit(span)[0] == unit


def test_timeline_of_a_track_log(tmp_path):
    line = timeline(read_log(track_log(tmp_path / "t.jsonl")).evaluations)
    assert line["time_unit"] == "min"  # 40 min of readings
    assert line["t"] == [0.0, 10.0, 20.0, 30.0, 40.0, None]
    beam = line["tracked"]["beam_x"]
    assert beam["unit"] == "µm" and beam["values"][0] is None
    assert beam["values"][1:] == pytest.approx([1.0, 2.0, 3.0, 4.0, 5.0], rel=1e-12)
    assert line["tracked"]["gain"]["values"][:2] == [None, 1.5]
    assert unit_groups(line["tracked"]) == [("µm", ["beam_x"]), ("1", ["gain"])]


def test_a_one_shot_log_has_times_and_nothing_tracked(tmp_path):
    with RunLog.create(tmp_path / "o.jsonl", {"knob_names": KNOBS, "method": "nm"}) as log:
        for k in range(3):
            log.log_evaluation(k, [0.0, 0.0], 1.0, t_read=T0 + 2.5 * k)
    line = timeline(read_log(tmp_path / "o.jsonl").evaluations)
    assert line == {"t": [0.0, 2.5, 5.0], "time_unit": "s", "tracked": {}}


def test_the_report_draws_the_run_against_time_with_one_panel_per_unit(tmp_path):
    log = track_log(tmp_path / "t.jsonl")
    data = run_report(log)
    fig, axes = draw_time(data)
    assert len(axes) == 3
    assert axes[0].get_ylabel() == "objective (mA/min)"
    assert axes[1].get_ylabel() == "tracked (µm)" and axes[2].get_ylabel() == "tracked (1)"
    assert axes[-1].get_xlabel() == "time since the first reading (min)"
    xs, ys = axes[1].lines[0].get_data()
    assert list(xs[1:5]) == [10.0, 20.0, 30.0, 40.0] and ys[4] == pytest.approx(4.0)
    plt.close(fig)
    png, page = write_report(log)
    assert png == tmp_path / "t_report.png"
    timed = tmp_path / "t_report_time.png"
    assert timed.read_bytes().startswith(b"\x89PNG")
    assert page.read_text().count("data:image/png;base64,") == 2


def test_the_dashboard_state_carries_the_timeline(tmp_path):
    s = run_state(track_log(tmp_path / "t.jsonl"))
    assert s["time_unit"] == "min" and s["t"][:3] == [0.0, 10.0, 20.0]
    assert s["tracked"]["beam_x"]["unit"] == "µm"


@pytest.mark.skipif(BROWSER is None, reason="no Chromium (apt-get install chromium)")
def test_the_final_page_plots_the_objective_and_the_tracked_unknowns_against_time(tmp_path):
    page = write_final_page(track_log(tmp_path / "t.jsonl"))
    browser = [BROWSER, "--headless", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
               f"--user-data-dir={tmp_path / 'profile'}", "--virtual-time-budget=3000"]  # fmt: skip
    dom = subprocess.run(
        [*browser, "--dump-dom", page.as_uri()], capture_output=True, text=True, timeout=90
    ).stdout
    assert dom.count("time since the first reading (min)") == 3  # objective, µm, 1
    assert "tracked (µm)" in dom and "tracked (1)" in dom and "beam_x" in dom
    assert 'id="tracked0"' in dom and 'id="tracked1"' in dom
