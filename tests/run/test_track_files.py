"""Run files of track mode (``mode: track``): the keys checked, the defaults, and `pigp
optimize` running a track run on the simulated ring until its count or time limit, then leaving
the knobs at the estimate; a one-shot run's ``restore: current``; a track run resumed."""

from __future__ import annotations

import time

import pytest
import yaml

from pigp_torch import cli
from pigp_torch.data.runlog import read_log
from pigp_torch.loop.config import ConfigError
from pigp_torch.loop.config.track import MAX_TIME_LIMIT_S, duration_s
from pigp_torch.loop.run import validate_config

KNOBS = ["01G-QSS4", "02G-QSS3"]


@pytest.fixture(autouse=True)
def private_locks(tmp_path, monkeypatch):
    monkeypatch.setenv("PIGP_LOCK_DIR", str(tmp_path / "locks"))
    modules = tuple(dict.fromkeys((*cli.COMMAND_MODULES, "optimize")))
    monkeypatch.setattr(cli, "COMMAND_MODULES", modules)


def track_file(**over) -> dict:
    data = {
        "machine": {"kind": "sim", "error_seed": 1, "noise": 0.04, "x_init": {"01G-QSS4": 2.0}},
        "knobs": {k: [-6.0, 6.0] for k in KNOBS},
        "method": {"name": "nelder-mead", "options": {"initial_simplex_size": 0.3}},
        "mode": "track",
        "time_limit": "1 h",
        "budget": 6,
        "max_step": 0.2,
        "log": "run.jsonl",
    }
    data.update(over)
    return data


@pytest.mark.parametrize(
    ("text", "seconds"),
    [("8 h", 28800.0), ("90 min", 5400.0), ("1.5 d", 129600.0), ("30s", 30.0), ("2e-1 s", 0.2)],
)
def test_a_time_limit_is_a_number_and_a_unit(text, seconds):
    assert duration_s(text) == pytest.approx(seconds, rel=1e-12)


@pytest.mark.parametrize("text", ["8", "8 hours", "h", 8, "-1 h"])
def test_a_time_limit_without_a_known_unit_is_refused(text):
    with pytest.raises(ValueError, match="is not a duration: give a number and a unit"):
        duration_s(text)


@pytest.mark.parametrize("text", ["0 h", "32 d"])
def test_a_time_limit_out_of_range_is_refused(text):
    with pytest.raises(ValueError, match="above 0 s and at most 31 d"):
        duration_s(text)
    assert duration_s("31 d") == MAX_TIME_LIMIT_S


def test_the_mode_decides_the_default_restore():
    assert validate_config(track_file()).restore == "estimate"
    assert validate_config(track_file(restore="best", best_window=5)).restore == "best"
    one_shot = track_file(mode="optimize")
    del one_shot["time_limit"]
    assert validate_config(one_shot).restore == "initial"
    del one_shot["mode"]
    config = validate_config(one_shot)
    assert config.mode == "optimize" and config.time_limit_s() is None


@pytest.mark.parametrize(
    ("over", "drop", "message"),
    [
        ({}, "time_limit", "time_limit: a track run needs a wall-clock limit"),
        ({"mode": "optimize"}, None, "time_limit is for mode: track"),
        ({"mode": "optimize", "restore": "estimate"}, "time_limit", "restore: estimate is for"),
        ({"time_limit": "8 hours"}, None, "is not a duration"),
        ({"mode": "shift"}, None, "mode"),
        ({"best_window": 0}, None, "best_window"),
    ],
)
def test_bad_track_keys_are_one_clear_error(over, drop, message):
    data = track_file(**over)
    if drop:
        del data[drop]
    with pytest.raises(ConfigError, match=message):
        validate_config(data)


def _run(tmp_path, capsys, *extra, **over) -> tuple[int, str]:
    path = tmp_path / "run.yaml"
    path.write_text(yaml.safe_dump(track_file(**over)))
    code = cli.main(["optimize", "--config", str(path), "--quiet", *extra])
    return code, capsys.readouterr()


def test_a_track_run_ends_at_its_count_with_the_knobs_at_the_estimate(tmp_path, capsys):
    """budget 6 (the count limit) well inside the hour: six readings, exit 0, and the knobs at
    Nelder–Mead's estimate (its best reading), which the end record names."""
    code, captured = _run(tmp_path, capsys)
    assert code == 0, captured.err
    assert "track mode: until stopped, 1 h (3600 s) or 6 readings" in captured.out
    log = read_log(tmp_path / "run.jsonl")
    end = log.last_end
    assert log.n_evaluations == 6 and end["reason"] == "max_readings (6) made"
    assert end["restored_to"] == "estimate" and end["restored"] is True
    best = max(log.evaluations, key=lambda e: e["y"])
    assert end["final_setpoints"] == best["x"] == end["restore_target"]
    assert all(e["tracked"] == {} for e in log.evaluations)  # Nelder–Mead tracks nothing


def test_a_track_run_ends_at_its_time_limit(tmp_path, capsys):
    t0 = time.monotonic()
    code, captured = _run(tmp_path, capsys, time_limit="1 s", budget=100_000)
    assert code == 0, captured.err
    end = read_log(tmp_path / "run.jsonl").last_end
    assert end["status"] == "completed" and "the time limit of 1 s passed" in end["reason"]
    assert 1 <= end["n_evaluations"] < 100_000 and time.monotonic() - t0 < 120


def test_a_one_shot_run_with_restore_current_leaves_the_knobs(tmp_path, capsys):
    data = {"mode": "optimize", "restore": "current", "budget": 4}
    path = tmp_path / "run.yaml"
    file = track_file(**data)
    del file["time_limit"]
    path.write_text(yaml.safe_dump(file))
    assert cli.main(["optimize", "--config", str(path), "--quiet"]) == 0
    log = read_log(tmp_path / "run.jsonl")
    assert log.last_end["final_setpoints"] == log.evaluations[-1]["x"] != [2.0, 0.0]


def test_a_track_run_resumes_with_a_larger_budget(tmp_path, capsys):
    code, _ = _run(tmp_path, capsys, budget=4)
    assert code == 0
    (tmp_path / "run.yaml").write_text(yaml.safe_dump(track_file(budget=7)))
    code = cli.main(["optimize", "--config", str(tmp_path / "run.yaml"), "--resume",
                     str(tmp_path / "run.jsonl"), "--quiet"])  # fmt: skip
    captured = capsys.readouterr()
    assert code == 0, captured.err
    log = read_log(tmp_path / "run.jsonl")
    assert log.n_evaluations == 7 and log.last_end["restored_to"] == "estimate"
    assert [e["step"] for e in log.evaluations] == list(range(7))
