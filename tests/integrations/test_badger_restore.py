"""The ``pigp_sim`` Badger environment puts the knobs back at the end of a routine, over real
Channel Access (the simulated IOC on 127.0.0.1), through Badger's own runners: headless
(``badger.core.run_routine``) and the GUI's routine process (``badger.core_subprocess``), on a
normal end, on Ctrl-C and on the GUI's Stop (SIGTERM). Each case runs ``badger_driver.py`` in a
subprocess with a fresh HOME."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("badger")
pytest.importorskip("caproto")

DRIVER = Path(__file__).with_name("badger_driver.py")


def _drive(case: str, tmp_path) -> dict:
    env = {**os.environ, "HOME": str(tmp_path), "QT_QPA_PLATFORM": "offscreen"}
    env.pop("EPICS_CA_ADDR_LIST", None)
    proc = subprocess.run(
        [sys.executable, str(DRIVER), case], capture_output=True, text=True, timeout=300,
        env=env, cwd=tmp_path,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


@pytest.mark.slow
def test_headless_routines_end_with_the_knobs_found_at_the_start(tmp_path):
    """After a routine of Badger's own loop, and after a Ctrl-C in the middle of one, the IOC's
    setpoints are exactly those found at the start, though the routine moved them by amps;
    with ``end_knobs: best`` they are the knobs of the highest loss rate read."""
    r = _drive("headless", tmp_path)
    initial = r["initial"]
    assert initial["n"] == 6 and initial["moved"] > 1.0  # the routine did move the knobs (A)
    assert initial["end"] == initial["start"] == r["start"]  # exact, as floats over CA
    best = r["best"]
    assert best["n"] == 6 and best["best"] != best["start"]  # a better point than the start
    assert best["end"] == best["best"]
    stopped = r["interrupt"]
    assert stopped["raised"] == "KeyboardInterrupt" and stopped["n"] == 3
    assert stopped["moved"] > 1.0 and stopped["end"] == r["start"]


@pytest.mark.slow
def test_gui_routines_end_with_the_knobs_found_at_the_start(tmp_path):
    """Badger's GUI runner (its routine process, fed as the GUI feeds it): at the end of a
    routine (max evaluations reached) and after the Stop button (stop event, then SIGTERM when
    the process is busy) the setpoints are exactly the start's."""
    r = _drive("gui", tmp_path)
    done = r["finished"]
    assert done["n"] == 4 and done["moved"] > 1.0 and done["exitcode"] == 0
    assert done["end"] == r["start"]
    stopped = r["stopped"]
    assert stopped["n"] >= 3 and stopped["moved"] > 1.0 and stopped["stopped_by"] is not None
    assert stopped["end"] == r["start"]


@pytest.mark.slow
def test_badger_core_routines_stopped_by_their_active_callback_end_at_the_start(tmp_path):
    """A script that runs a routine with Badger's own ``badger.core.run_routine`` in its own
    process and stops it through the active callback: the IOC's setpoints end exactly at the
    start whether the script catches Badger's stop and exits, dies of it (exit 1), or drops the
    routine and collects the garbage (restored while the process still runs, no exit hook)."""
    r = _drive("core", tmp_path)
    for how in ("caught", "uncaught", "gc"):
        case = r[how]
        assert case["end"] == r["start"], (how, case)
    assert r["caught"]["returncode"] == 0 and r["caught"]["n"] == 4
    assert r["caught"]["moved"] > 1.0  # the routine did move the knobs (A)
    assert r["uncaught"]["returncode"] == 1
    assert r["gc"]["returncode"] == 0 and r["gc"]["inside"] == r["start"]
