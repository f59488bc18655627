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

from pigp_torch.data.runlog import RunLog
from pigp_torch.reporting.dashboard import Dashboard, run_state

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
        assert s["objective_unit"] == "mA/min" and s["knob_unit"] == "A"  # the defaults
        assert s["x"] == [[0.0, 0.0], [0.5, -1.0], [1.0, -2.0]] and not s["ended"]
        log.write("notice", step=2, message="a notice")
        log.log_end("completed", reason="budget reached", restored_to="initial")
    s = run_state(tmp_path / "run.jsonl")
    assert s["status"] == "completed" and s["ended"]
    assert s["notices"] == [
        "evaluation 3: a notice",
        "ended completed: budget reached; knobs restored to initial",
    ]


def test_a_beam_logged_in_metres_is_shown_in_micrometres_with_per_knob_units(tmp_path):
    """An ARES-EA log keeps m; the page shows µm, and each knob's own unit."""
    header = {
        "knob_names": ["Q1", "H1"],
        "knob_units": ["1/m^2", "rad"],
        "method": "ares-physics",
        "maximize": False,
        "config": {"objective_unit": "m", "knob_unit": "1/m^2 or rad"},
    }
    with RunLog.create(tmp_path / "ares.jsonl", header) as log:
        log.log_start([0.0, 0.0], budget=5, first_step=0)
        log.log_evaluation(0, [1.0, 1e-3], 8.25e-7)
        log.log_evaluation(1, [2.0, 2e-3], 4.5e-7)
        s = run_state(log.path)
    assert s["objective_unit"] == "µm" and s["knob_units"] == ["1/m^2", "rad"]
    assert s["y"] == pytest.approx([0.825, 0.45], rel=1e-12) and s["best_y"] == pytest.approx(0.45)


def test_final_page_embeds_the_state_and_needs_no_server(tmp_path):
    """The final page: the state as JSON in the page (a '</script>' in a knob name cannot end the
    script), no polling, written next to the log."""
    from pigp_torch.reporting.dashboard import final_page_path, page_html, write_final_page

    with make_log(tmp_path / "run.jsonl", 3) as log:
        log.log_end("completed")
    path = write_final_page(tmp_path / "run.jsonl")
    assert path == final_page_path(tmp_path / "run.jsonl") == tmp_path / "run_dashboard.html"
    text = path.read_text()
    embedded = text.split("const INITIAL = ")[1].split(";\n")[0]
    state = json.loads(embedded)
    assert state["n"] == 3 and state["final_page"] == str(path) and state["ended"]
    evil = page_html(state={"knob_names": ["</script><b>x"]})
    assert "</script><b>" not in evil and "<\\/script><b>x" in evil
    assert "const INITIAL = null;" in page_html(250) and "const POLL_MS = 250;" in page_html(250)


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


@pytest.mark.skipif(BROWSER is None, reason="no Chromium (apt-get install chromium)")
def test_the_page_has_axes_units_knobs_and_keeps_the_final_state(tmp_path):
    """While the page polls, the run ends: the page shows numbered axes with units, the knob
    panel and the notices, stops polling and names the final page; finish() returns as soon as
    the page has the final state (well before its 20 s bound), and the written final page shows
    the same without a server."""
    import threading
    import time

    log = make_log(tmp_path / "run.jsonl", 4)
    finished = {}

    def end_the_run(state):  # the second poll: the run ends, the command finishes the dashboard
        if dash.requests == 2 and not finished:
            log.write("notice", step=3, message="physics prior rejected")
            log.log_end("completed", restored_to="initial")
            log.close()
            t0 = time.monotonic()
            finished["thread"] = threading.Thread(
                target=lambda: finished.update(path=dash.finish(linger_s=20),
                                               dt=time.monotonic() - t0))  # fmt: skip
            finished["thread"].start()

    dash = Dashboard(log.path, poll_ms=200, lifetime_s=120, on_state=end_the_run)
    browser = [BROWSER, "--headless", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
               f"--user-data-dir={tmp_path / 'profile'}", "--virtual-time-budget=4000"]  # fmt: skip
    try:
        dom = subprocess.run(
            [*browser, "--dump-dom", dash.url], capture_output=True, text=True, timeout=90
        ).stdout
    finally:
        finished["thread"].join(timeout=30)
        dash.close()
    final = tmp_path / "run_dashboard.html"
    assert finished["path"] == final and finished["dt"] < 15
    browser[5] = f"--user-data-dir={tmp_path / 'profile2'}"  # a fresh profile for a file URL
    static = subprocess.run(
        [*browser, "--dump-dom", final.as_uri()], capture_output=True, text=True, timeout=90
    ).stdout
    for where, text in (("live page", dom), ("final file", static)):
        assert "The run has ended (completed)" in text, where
        assert str(final) in text, where
        assert "objective (mA/min)" in text and "knob setting (A)" in text
        assert text.count('class="ytick"') >= 3 and text.count('class="xtick"') >= 3
        assert "last setting (A)" in text and "01G-QSS4" in text and "02G-QSS3" in text
        assert ">0.700000 mA/min<" in text  # the best reading (0.5, 0.4, 0.7, 0.2), with its unit
        assert "evaluation 4: physics prior rejected" in text
        assert "knobs restored to initial" in text


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
    final = tmp_path / "run_dashboard.html"
    assert f"dashboard: final page {final}" in out
    assert "step 3 of 3" not in final.read_text()  # drawn by the page's script, from the state
    state = json.loads(final.read_text().split("const INITIAL = ")[1].split(";\n")[0])
    assert state["n"] == 3 and state["status"] == "completed" and state["knob_unit"] == "A"
