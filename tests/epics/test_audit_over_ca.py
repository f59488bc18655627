"""Faults found by an outside audit that the other fault tests do not cover, over real Channel
Access and judged by the IOC's own put log: a glitch of the objective during the best-point
confirmation of ``restore: best``.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time

import pytest
import torch
import yaml

from pigp_torch import cli
from pigp_torch.data.runlog import read_log
from tests.epics.test_faults_over_ca import (
    fault_at_read,
    final_setpoints,
    run,
    start_of,
    worst_step,
    write_config,
)


@pytest.fixture(autouse=True)
def private_locks(tmp_path, monkeypatch):
    monkeypatch.setenv("PIGP_LOCK_DIR", str(tmp_path / "locks"))


@pytest.fixture
def with_optimize(monkeypatch):
    modules = tuple(dict.fromkeys((*cli.COMMAND_MODULES, "optimize")))
    monkeypatch.setattr(cli, "COMMAND_MODULES", modules)


@pytest.mark.slow  # a 5-evaluation run with ramps and a restore: ~10-20 s on a busy host
def test_a_glitch_during_the_best_confirmation_restores_the_initial_setpoints(
    ioc, probe, ring, tmp_path, capsys, with_optimize
):
    """Every objective read after the last evaluation returns 1e30 (the glitch starts while the
    best point is being confirmed): the confirmation readings are discarded as outside the PV's
    range, the best is NOT confirmed, and the knobs go back exactly to the initial setpoints,
    every put within max_step; no evaluation is a glitch."""
    budget = 5
    probe.write_many(ioc.setpoint_pvs[:2], start_of(ring))
    mark = ioc.n_puts()
    config = write_config(tmp_path, ioc, ring, restore="best", objective_noise=0.04, budget=budget)
    with fault_at_read(budget + 1, lambda: probe.write(ioc.glitch_readings_pv, 50)):
        with pytest.warns(UserWarning, match="restoring the initial knobs instead"):
            code, captured = run(config, capsys)
    assert code == 0, captured.err
    log = read_log(tmp_path / "run.jsonl")
    assert log.n_evaluations == budget and float(log.Y().max()) < 5.0
    assert log.discarded, "the glitched confirmation readings were not logged as discarded"
    assert all(d["y"] == 1e30 for d in log.discarded)
    assert all(d["reason"].startswith("confirming the best point:") for d in log.discarded)
    end = log.last_end
    assert end["best_confirmation"]["confirmed"] is False
    assert end["restored_to"] == "initial (best not confirmed)" and end["restored"] is True
    assert final_setpoints(ioc, mark) == start_of(ring).tolist()  # the IOC's last puts
    assert torch.equal(probe.read_many(ioc.setpoint_pvs[:2]), start_of(ring))
    assert worst_step(ioc, mark) <= 1 + 1e-9


def _records(path) -> list[dict]:
    """The run log's complete records so far (a line being written is skipped)."""
    out = []
    if path.exists():
        for line in path.read_text().splitlines():
            with contextlib.suppress(ValueError):
                out.append(json.loads(line))
    return out


def _wait_until(predicate, timeout: float, what: str, proc) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return
        if proc.poll() is not None:
            break
        time.sleep(0.02)
    raise AssertionError(f"{what} not within {timeout:g} s (run exit {proc.poll()})")


@pytest.mark.slow  # two IOC starts and a run in a subprocess: ~30-60 s
def test_an_ioc_restarted_during_the_restore_is_ramped_from_its_power_on_setpoints(tmp_path):
    """`pigp optimize` (a subprocess) is stopped by SIGTERM with the knobs at least 3 steps from
    where they were found; when the restore's first intent is logged the IOC is killed, and a
    new IOC is started on the same port with every setpoint at its power-on value (0 A, not the
    last one the run acknowledged). The restore's next attempts ramp from the setpoints the new
    IOC holds: no put either IOC received exceeds max_step, and the new IOC ends exactly at the
    initial setpoints (exit 143, end record restored)."""
    from caproto.threading.client import Context

    from pigp_torch.testing.ca_env import client_environment, free_port
    from pigp_torch.testing.ioc import start_sim_ioc

    knobs, start, limit = ["01G-QSS4", "02G-QSS3"], [12.0, -9.0], 0.1 * 30.0
    port = free_port()
    config = {
        "machine": {"kind": "epics", "settle_time": 0.1, "timeout": 1.0, "stale_timeout": 1.0},
        "knobs": {k: [-30.0, 30.0] for k in knobs},
        "objective": {"pv": "SPEAR:BeamLossRate"},
        "method": {"name": "nelder-mead", "options": {"initial_simplex_size": 0.3}},
        "budget": 200,
        "max_step": 0.1,
        "log": "run.jsonl",
        "lock_dir": "locks",
        "restore_attempts": 100,
        "restore_interval": 0.5,
    }
    (tmp_path / "run.yaml").write_text(yaml.safe_dump(config))
    log = tmp_path / "run.jsonl"
    env = {**os.environ, **client_environment(port), "OMP_NUM_THREADS": "1"}
    child = (
        "import sys; import pigp_torch.cli as c; "
        "c.COMMAND_MODULES = tuple(dict.fromkeys((*c.COMMAND_MODULES, 'optimize'))); "
        "sys.exit(c.main(sys.argv[1:]))"
    )
    cmd = [sys.executable, "-c", child, "optimize", "--config", "run.yaml", "--quiet"]
    run = None
    try:
        with start_sim_ioc(1, port, knobs=knobs, update_period=0.05) as first:
            context = Context(timeout=5.0)
            try:
                for name, value in zip(first.setpoint_pvs, start, strict=True):
                    (pv,) = context.get_pvs(name, timeout=5.0)
                    pv.wait_for_connection(timeout=5.0)
                    pv.write([value], wait=True, timeout=5.0)
            finally:
                context.disconnect(wait=False)
            mark = first.n_puts()  # the puts above set the start; the run's come after
            run = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                   env=env, cwd=tmp_path)  # fmt: skip

            def far() -> bool:  # an evaluation >= 3 steps from the start on some knob
                return any(
                    r.get("type") == "evaluation"
                    and max(abs(a - b) for a, b in zip(r["x"], start, strict=True)) >= 3 * limit
                    for r in _records(log)
                )

            _wait_until(far, 120.0, "an evaluation 3 steps away", run)
            run.send_signal(signal.SIGTERM)

            def restoring() -> bool:
                return any(
                    r.get("type") == "intent" and r.get("purpose", "").startswith("restore")
                    for r in _records(log)
                )

            _wait_until(restoring, 30.0, "the restore's first intent", run)
            first.kill()
            first_puts = first.puts(mark)
        with start_sim_ioc(1, port, knobs=knobs, update_period=0.05) as second:
            out, _ = run.communicate(timeout=180)
            second_puts = second.puts()
        text = out.decode(errors="replace")
        assert run.returncode == 128 + signal.SIGTERM, text
        assert second_puts, "the restore ended before the IOC died: no put reached the new IOC"
        assert second_puts[0]["previous"] == 0.0  # power-on: not what the run last acknowledged
        for entries in (first_puts, second_puts):
            worst = max(abs(e["value"] - e["previous"]) for e in entries if "knob" in e)
            assert worst <= limit * (1 + 1e-9), (worst, entries[-6:])
        last = {e["knob"]: e["value"] for e in second_puts if "knob" in e}
        assert [last[k] for k in knobs] == start  # exactly, at the new IOC
        end = read_log(log).last_end
        assert end["restored"] is True and end["final_setpoints"] == start
    finally:
        if run is not None and run.poll() is None:
            run.kill()
            run.wait(timeout=10)
