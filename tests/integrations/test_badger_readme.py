"""The README's Badger recipe, command by command, as a new user runs it: a fresh HOME (no
``~/.config``), a fresh virtual environment layered on the installed one (so that ``pigp
badger-setup`` writes its start-up file there, not into the shared environment), every command
a subprocess with a time limit. ``pigp`` and ``badger`` run as ``python -m pigp_torch.cli`` and
``python -m badger`` of that environment (the same entry points as the console scripts)."""

from __future__ import annotations

import signal
import subprocess
import time
from pathlib import Path

import pytest

pytest.importorskip("badger")
pytest.importorskip("caproto")

REPO = Path(__file__).resolve().parents[2]


@pytest.mark.slow
def test_the_readme_badger_recipe_on_a_fresh_home(tmp_path, layered_python, fresh_home_env):
    """badger-setup on a fresh HOME; Badger's own CLI then lists pigp_physics and pigp_sim; a
    headless pigp_physics routine on pigp_sim against `pigp serve-sim` moves the knobs and ends
    with the IOC's setpoints exactly where they were."""
    import pigp_torch.integrations.badger as pb
    from pigp_torch.simulated_epics.ca_env import client_environment, free_port, patched_environ

    python, env = layered_python, fresh_home_env
    home = Path(env["HOME"])

    def run(*args, timeout=180):
        proc = subprocess.run(
            [str(python), *args], capture_output=True, text=True, timeout=timeout, env=env,
            cwd=tmp_path,
        )  # fmt: skip
        assert proc.returncode == 0, (args, proc.stdout[-2000:], proc.stderr[-3000:])
        return proc.stdout

    before = run("-m", "badger", "generator")  # Badger not configured yet: it says so, exits 0
    assert "pigp_physics" not in before
    out = run("-m", "pigp_torch.cli", "badger-setup")
    assert str(home / ".config" / "config.yaml") in out
    assert str(Path(str(python)).parents[1]) in out  # the start-up file went into this venv
    assert "- pigp_physics" in run("-m", "badger", "generator").splitlines()
    assert "pigp_sim" in run("-m", "badger", "env")
    assert "prior" in run("-m", "badger", "generator", "pigp_physics")

    d = len(pb.SIM_KNOBS)  # the routine runs with the shipped prior, as the README's command
    port = free_port()
    ioc = subprocess.Popen(
        [str(python), "-m", "pigp_torch.cli", "serve-sim", "--port", str(port)],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env, cwd=tmp_path,
    )  # fmt: skip
    try:
        from caproto.threading.client import Context

        start = [round(0.75 * k - 4.0, 6) for k in range(d)]
        names = [f"{k}:CurrSetpt" for k in pb.SIM_KNOBS]
        with patched_environ(client_environment(port)):
            ctx = Context(timeout=5.0)
            deadline = time.monotonic() + 120.0
            while True:  # the ring is built before the server answers
                try:
                    pvs = ctx.get_pvs(*names, timeout=5.0)
                    for pv in pvs:
                        pv.wait_for_connection(timeout=5.0)
                    break
                except TimeoutError:
                    assert ioc.poll() is None and time.monotonic() < deadline, "IOC not up"
            for pv, value in zip(pvs, start, strict=True):
                pv.write([value], wait=True, timeout=5.0)
            out = run(
                str(REPO / "examples" / "badger_routine.py"), "--ca-port", str(port),
                "--evaluations", "5", timeout=300,
            )  # fmt: skip
            end = [float(pv.read(timeout=5.0).data[0]) for pv in pvs]
            ctx.disconnect()
    finally:
        ioc.send_signal(signal.SIGTERM)
        try:
            ioc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            ioc.kill()
            ioc.wait(timeout=20)
    rows = [line for line in out.splitlines() if line.startswith("|  ") and "iter" not in line]
    assert len(rows) == 5  # Badger's table: the start and 4 proposals
    moved = max(
        abs(float(v) - s)
        for line in rows
        for v, s in zip(line.strip("| ").split("|")[2:], start, strict=True)
    )
    assert moved > 1.0  # the routine moved the knobs by amps ...
    assert end == start  # ... and left them exactly where it found them
