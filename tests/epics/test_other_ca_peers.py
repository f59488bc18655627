"""Channel Access with peers other than our own caproto code: `pigp optimize` against a real
EPICS base IOC (pythonSoftIOC) with a SIGTERM mid-run, and the simulated IOC (`pigp serve-sim`)
read and written by pyepics, the reference client built on EPICS base's libca.

Everything listens and searches on 127.0.0.1 only; each peer runs in a subprocess, and every
wait is bounded.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
import yaml

from pigp_torch.simulated_epics.ca_env import client_environment, free_port, server_environment

HERE = Path(__file__).parent
KNOBS = ["01G-QSS4", "02G-QSS3"]
CHILD = (
    "import sys; import pigp_torch.cli as c; "
    "c.COMMAND_MODULES = tuple(dict.fromkeys((*c.COMMAND_MODULES, 'optimize'))); "
    "sys.exit(c.main(sys.argv[1:]))"
)


def read_puts(path: Path) -> list[dict]:
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def wait_until(predicate, timeout: float, what: str, proc=None) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return
        if proc is not None and proc.poll() is not None:
            break
        time.sleep(0.05)
    raise AssertionError(f"{what} not within {timeout:g} s")


@pytest.mark.slow
def test_optimize_then_sigterm_against_a_real_epics_base_ioc(tmp_path):
    """A short `pigp optimize` over CA against a pythonSoftIOC IOC (EPICS base's own CA
    server), stopped by SIGTERM after a few evaluations: exit 143, and the IOC's put log shows
    the setpoints put back exactly to where they were, no put above max_step."""
    pytest.importorskip("softioc")
    port = free_port()
    start = [2.5, -1.25]
    puts = tmp_path / "puts.jsonl"
    env = {**os.environ, **server_environment(port), "EPICS_CA_ADDR_LIST": "127.0.0.1",
           "EPICS_CA_AUTO_ADDR_LIST": "NO"}  # fmt: skip
    ioc_out = open(tmp_path / "ioc.txt", "w")
    ioc = subprocess.Popen(
        [sys.executable, str(HERE / "softioc_ring.py"), "--put-log", str(puts), "--x-init",
         ",".join(map(str, start))],
        stdin=subprocess.DEVNULL, stdout=ioc_out, stderr=subprocess.STDOUT, env=env,
    )  # fmt: skip
    run = None
    try:
        wait_until(lambda: "softioc ready" in (tmp_path / "ioc.txt").read_text(), 60.0,
                   "the softioc IOC ready", ioc)  # fmt: skip
        config = {
            "machine": {"kind": "epics", "settle_time": 0.1, "timeout": 2.0, "stale_timeout": 2.0},
            "knobs": {k: [-15.0, 15.0] for k in KNOBS},
            "objective": {"pv": "TEST:BeamLossRate"},
            "method": {"name": "nelder-mead", "options": {"initial_simplex_size": 0.3}},
            "budget": 500,
            "max_step": 0.2,
            "objective_noise": 0.01,
            "log": "run.jsonl",
            "lock_dir": "locks",
        }
        (tmp_path / "run.yaml").write_text(yaml.safe_dump(config))
        client = {**os.environ, **client_environment(port), "OMP_NUM_THREADS": "1",
                  "OPENBLAS_NUM_THREADS": "1"}  # fmt: skip
        log = tmp_path / "run.jsonl"
        run = subprocess.Popen(
            [sys.executable, "-c", CHILD, "optimize", "--config", str(tmp_path / "run.yaml"),
             "--quiet"],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=client, cwd=tmp_path,
        )  # fmt: skip
        wait_until(
            lambda: log.exists() and log.read_text().count('"type":"evaluation"') >= 4,
            120.0, "four evaluations", run,
        )  # fmt: skip
        run.send_signal(signal.SIGTERM)
        out, _ = run.communicate(timeout=60)
        text = out.decode(errors="replace")
        assert run.returncode == 128 + signal.SIGTERM, text
        assert "knobs restored to initial" in text
        entries = read_puts(puts)
        moved = {e["knob"] for e in entries if e["value"] != e["previous"]}
        assert moved == set(KNOBS)  # the run did move both knobs before it was stopped
        last = {e["knob"]: e["value"] for e in entries}
        assert [last[k] for k in KNOBS] == start  # exactly, at the IOC
        worst = max(abs(e["value"] - e["previous"]) for e in entries)
        assert worst <= 0.2 * 15.0 * (1 + 1e-9), worst
        from pigp_torch.data.runlog import read_log

        end = read_log(log).last_end
        assert end["restored"] is True and end["final_setpoints"] == start
    finally:
        if run is not None and run.poll() is None:
            run.kill()
            run.wait(timeout=10)
        ioc.send_signal(signal.SIGTERM)
        try:
            ioc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            ioc.kill()
            ioc.wait(timeout=10)
        ioc_out.close()


PYEPICS_SCRIPT = textwrap.dedent(
    """
    import json, sys
    import epics
    sp, rb, loss = sys.argv[1:4]
    out = {"sp0": epics.caget(sp, timeout=5.0), "loss": epics.caget(loss, timeout=5.0)}
    out["put"] = epics.caput(sp, 1.5, wait=True, timeout=5.0)
    ctrl = epics.PV(sp).get_ctrlvars(timeout=5.0)
    out["limits"] = [float(ctrl["lower_ctrl_limit"]), float(ctrl["upper_ctrl_limit"])]
    out["units"] = ctrl["units"]
    import time
    deadline = time.monotonic() + 5.0
    while time.monotonic() < deadline:
        out["rb"] = epics.caget(rb, timeout=5.0, use_monitor=False)
        if out["rb"] == 1.5:
            break
        time.sleep(0.05)
    out["sp1"] = epics.caget(sp, timeout=5.0, use_monitor=False)
    print("RESULT " + json.dumps(out), flush=True)
    """
)


def test_serve_sim_answers_pyepics(ioc, probe, ring):
    """pyepics (libca) reads the knob setpoint, its control limits and the loss rate of the
    simulated IOC, puts a setpoint with completion, and sees the readback follow; the IOC's
    put log holds that put."""
    pytest.importorskip("epics")
    mark = ioc.n_puts()
    sp, rb = ioc.setpoint_pvs[0], ioc.readback_pvs[0]
    env = {**os.environ, **client_environment(ioc.port)}
    proc = subprocess.run(
        [sys.executable, "-c", PYEPICS_SCRIPT, sp, rb, ioc.loss_rate_pv],
        capture_output=True, text=True, env=env, timeout=60,
    )  # fmt: skip
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")]
    assert proc.returncode == 0 and lines, proc.stdout + proc.stderr
    got = json.loads(lines[-1][len("RESULT ") :])
    assert got["sp0"] == 0.0 and got["put"] == 1
    assert got["sp1"] == got["rb"] == 1.5
    assert got["limits"] == [float(ring.bounds[0, 0]), float(ring.bounds[1, 0])]
    assert got["units"] == "A"
    assert abs(got["loss"] - float(ring.loss_rate(ring.bounds[0] * 0))) < 5 * 0.04
    assert probe.read(sp) == 1.5
    assert [(p["pv"], p["value"], p["previous"]) for p in ioc.puts(mark)] == [(sp, 1.5, 0.0)]
