"""The live page of a run (`pigp optimize --dashboard`): its state from the run log, the server on
127.0.0.1, and the page in a real headless browser (Chromium) updating after new evaluations."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import urllib.request
from pathlib import Path

import pytest

from pigp_torch.dashboard import Dashboard, run_state
from pigp_torch.runlog import RunLog

KNOBS = ["01G-QSS4", "02G-QSS3"]
BROWSER = shutil.which("chromium") or shutil.which("chromium-browser")


def make_log(path: Path, n: int, budget: int = 10) -> RunLog:
    log = RunLog.create(path, {"knob_names": KNOBS, "method": "pigp-physics", "maximize": True})
    log.log_start([0.0, 0.0], budget=budget, first_step=0)
    add(log, 0, n)
    return log


def add(log: RunLog, first: int, n: int) -> None:
    for k in range(first, first + n):
        log.log_evaluation(k, [0.5 * k, -1.0 * k], 0.5 + 0.1 * k * (-1) ** k)


def test_state_of_a_run_log(tmp_path):
    assert run_state(tmp_path / "none.jsonl")["status"] == "waiting"
    with make_log(tmp_path / "run.jsonl", 3) as log:
        s = run_state(log.path)
        assert (s["n"], s["budget"], s["status"]) == (3, 10, "running")
        assert s["best"] == [0.5, 0.5, 0.7] and s["move"] == 1.0 and s["move_knob"] == "02G-QSS3"
        log.log_end("completed")
    assert run_state(tmp_path / "run.jsonl")["status"] == "completed"


def test_server_answers_on_loopback_and_stops(tmp_path):
    with pytest.raises(ValueError, match="loopback"):
        Dashboard(tmp_path / "run.jsonl", host="0.0.0.0")
    make_log(tmp_path / "run.jsonl", 2).close()
    with Dashboard(tmp_path / "run.jsonl", lifetime_s=30) as dash:
        assert dash.url.startswith("http://127.0.0.1:")
        page = urllib.request.urlopen(dash.url, timeout=5).read().decode()
        assert (
            "state.json" in page and "<script>" in page and "http" not in page.split("<script>")[1]
        )
        state = json.loads(urllib.request.urlopen(dash.url + "state.json", timeout=5).read())
        assert state["n"] == 2
    with pytest.raises(OSError):
        urllib.request.urlopen(dash.url, timeout=2)
    short = Dashboard(tmp_path / "run.jsonl", lifetime_s=0.2)
    short._thread.join(timeout=5)  # the lifetime timer stopped it
    assert not short._thread.is_alive()


@pytest.mark.skipif(BROWSER is None, reason="no Chromium (apt-get install chromium)")
def test_the_page_in_headless_chromium_shows_and_follows_the_run(tmp_path):
    """The page loads, shows step 3 of 10, and after two more evaluations are logged (while the
    page polls) shows step 5 of 10 without a reload; a screenshot goes to the artifacts folder
    ($PIGP_TEST_ARTIFACTS, else the test's tmp folder)."""
    log = make_log(tmp_path / "run.jsonl", 3)
    grown = []

    def grow(state):  # the third poll: the run goes on by two evaluations
        if len(grown) == 0 and dash.requests == 3:
            add(log, 3, 2)
            grown.append(state["n"])

    dash = Dashboard(log.path, poll_ms=200, lifetime_s=120, on_state=grow)
    browser = [BROWSER, "--headless", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
               f"--user-data-dir={tmp_path / 'profile'}", "--virtual-time-budget=4000"]  # fmt: skip
    try:
        dom = subprocess.run(
            [*browser, "--dump-dom", dash.url], capture_output=True, text=True, timeout=90
        ).stdout
        assert grown == [3], "the page did not poll three times"
        assert "step 5 of 10" in dom and ">3,5<" in dom.replace("</span>", "<").replace(
            '<span id="seen">', ">"
        )
        artifacts = Path(os.environ.get("PIGP_TEST_ARTIFACTS") or tmp_path)
        artifacts.mkdir(parents=True, exist_ok=True)
        shot = artifacts / "dashboard.png"
        subprocess.run(
            [*browser, "--window-size=800,560", f"--screenshot={shot}", dash.url],
            capture_output=True, timeout=90,
        )  # fmt: skip
        assert shot.read_bytes().startswith(b"\x89PNG")
    finally:
        dash.close()
        log.close()


def test_pigp_optimize_dashboard_prints_its_url_and_stops(tmp_path, capsys):
    import yaml

    from pigp_torch import cli

    config = {
        "machine": {"kind": "sim", "error_seed": 1, "noise": 0.04, "seed": 2},
        "knobs": {k: [-30, 30] for k in KNOBS},
        "method": {"name": "nelder-mead"},
        "budget": 3,
        "max_step": 0.2,
        "log": "run.jsonl",
    }
    (tmp_path / "run.yaml").write_text(yaml.safe_dump(config))
    assert cli.main(["optimize", "--config", str(tmp_path / "run.yaml"), "--dashboard"]) == 0
    out = capsys.readouterr().out
    url = next(w for w in out.split() if w.startswith("http://127.0.0.1:"))
    assert "evaluation    3/3" in out
    with pytest.raises(OSError):  # stopped with the run
        urllib.request.urlopen(url, timeout=2)
