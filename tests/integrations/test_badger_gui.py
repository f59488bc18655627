"""Badger's own GUI under Xvfb, as an operator uses it, after the README's ``pigp badger-setup``
in a fresh HOME: its generator list shows ``pigp_physics`` (nothing imported by hand: the
start-up hook does it), and a routine template on ``pigp_sim`` (simulated IOC on 127.0.0.1) runs
through the GUI's run monitor and routine process, to its termination condition and again to
the Stop button, and ends both times with the IOC's setpoints exactly where they were.
Screenshots of the X screen are written (see ``badger_gui_driver.py``). Skipped without Xvfb
(``xvfb-run``) or PyQt5's X11 libraries."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest

pytest.importorskip("badger")
pytest.importorskip("caproto")
pytest.importorskip("PyQt5")

DRIVER = Path(__file__).with_name("badger_gui_driver.py")


@pytest.mark.slow
def test_badger_gui_lists_pigp_physics_and_runs_a_routine(tmp_path, layered_python, fresh_home_env):
    if shutil.which("xvfb-run") is None:
        pytest.skip("Xvfb is not installed (apt-get install xvfb)")
    import torch

    import pigp_torch.integrations.badger as pb
    from pigp_torch.prior import PhysicsPrior

    env = {**fresh_home_env}
    env.pop("QT_QPA_PLATFORM")  # the real X11 platform, on Xvfb's display
    setup = subprocess.run(
        [str(layered_python), "-m", "pigp_torch.cli", "badger-setup"], capture_output=True,
        text=True, timeout=120, env=env, cwd=tmp_path,
    )  # fmt: skip
    assert setup.returncode == 0, setup.stderr[-3000:]
    d = len(pb.SIM_KNOBS)
    PhysicsPrior(
        x0=torch.zeros(d, dtype=torch.float64), f_x0=1.5, f_inf=0.2,
        precision=2e-3 * torch.eye(d, dtype=torch.float64), amplitude=0.1, noise=0.04,
        knob_names=list(pb.SIM_KNOBS),
        bounds=torch.tensor([[-30.0] * d, [30.0] * d], dtype=torch.float64),
    ).save(tmp_path / "prior.json")  # fmt: skip
    out = tmp_path / "shots"
    proc = subprocess.run(
        ["xvfb-run", "-a", "-s", "-screen 0 1920x1080x24", str(layered_python), str(DRIVER),
         str(out), "--run", str(tmp_path / "prior.json")],
        capture_output=True, text=True, timeout=420, env=env, cwd=tmp_path,
    )  # fmt: skip
    if "could not load the qt platform plugin" in proc.stderr.lower():
        pytest.skip("PyQt5's X11 platform plugin lacks system libraries (libxcb-*)")
    assert proc.returncode == 0, proc.stderr[-4000:]
    r = json.loads(proc.stdout.strip().splitlines()[-1])
    assert "pigp_physics" in r["generators"] and r["selected"] == "pigp_physics"
    assert r["finished"] and r["n"] == 5  # the termination condition: 5 evaluations
    assert r["moved"] > 1.0  # the routine moved the knobs by amps ...
    assert r["end"] == r["start"]  # ... and the routine's end set them back exactly
    stopped = r["stopped"]  # the same routine again, stopped with the Stop button
    assert stopped["n"] >= 3 and not stopped["running"] and stopped["end"] == r["start"]
    from PIL import Image

    for name in ("generators.png", "algorithm.png", "run.png"):
        with Image.open(out / name) as img:
            assert img.size == (1920, 1080)
            lo, hi = img.convert("L").getextrema()
            assert hi - lo > 100  # a drawn window, not a blank screen
