"""Online safety over real Channel Access (the shared simulated IOC on 127.0.0.1): a crash and a
resume, two runs on one log or machine, an IOC reboot during a reading, a frozen objective PV,
a restore that fails, a PV that does not exist.

Runs go through `pigp optimize` (in this process, or in a child process where the test needs
to kill it) or through :func:`pigp_torch.optimize` with an ``EpicsMachine``; every wait is
bounded in time.
"""

from __future__ import annotations

import itertools
import os
import signal
import subprocess
import sys
import time

import pytest
import torch
import yaml

from pigp_torch import cli, optimize
from pigp_torch.data.runlog import read_log
from pigp_torch.machine.epics import EpicsMachine
from pigp_torch.machine.errors import MachineError, ReadError
from pigp_torch.optimizers import NelderMead

from .ca_runs import KNOBS, start_of, write_config
from .conftest import FAST


@pytest.fixture(autouse=True)
def private_locks(tmp_path, monkeypatch):
    """Machine locks in this test's folder (not the host's shared one)."""
    monkeypatch.setenv("PIGP_LOCK_DIR", str(tmp_path / "locks"))


@pytest.fixture
def with_optimize(monkeypatch):
    modules = tuple(dict.fromkeys((*cli.COMMAND_MODULES, "optimize")))
    monkeypatch.setattr(cli, "COMMAND_MODULES", modules)


CHILD = (
    "import sys; import pigp_torch.cli as c; "
    "c.COMMAND_MODULES = tuple(dict.fromkeys((*c.COMMAND_MODULES, 'optimize'))); "
    "sys.exit(c.main(sys.argv[1:]))"
)


def wait_for_evaluations(proc, log_path, n, timeout=90.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and proc.poll() is None:
        if log_path.exists() and log_path.read_text().count('"type":"evaluation"') >= n:
            return
        time.sleep(0.05)
    raise AssertionError(f"the child run did not log {n} evaluations (rc {proc.poll()})")


def test_a_crash_then_a_second_run_then_a_resume(ioc, probe, ring, tmp_path, capsys, with_optimize):
    """A run is SIGKILLed mid-run over CA. While it lives, a second `--resume` of its log and a
    second run on the same PVs (another log) are refused with exit 4, naming the holder. After
    the kill the log's last intent is the last setting commanded; the resume restores the knobs
    of the first start (not the crash point), says where the knobs stand, and ends there."""
    start = start_of(ring)
    probe.write_many(ioc.setpoint_pvs[:2], start)
    config = write_config(tmp_path, ioc, ring, budget=100_000)
    log_path = tmp_path / "run.jsonl"
    env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}
    with open(tmp_path / "err.txt", "w") as err:
        proc = subprocess.Popen(
            [sys.executable, "-c", CHILD, "optimize", "--config", config, "--quiet"],
            stdout=subprocess.DEVNULL,
            stderr=err,
            env=env,
        )
    try:
        wait_for_evaluations(proc, log_path, 3)
        # a second writer of the same log
        assert cli.main(["optimize", "--resume", str(log_path), "--config", config]) == 4
        message = capsys.readouterr().err
        assert f"run log {log_path} is in use by PID {proc.pid}" in message
        # a second run on the same machine, with another log
        other = write_config(tmp_path, ioc, ring, name="other.yaml", log="other.jsonl")
        assert cli.main(["optimize", "--config", other]) == 4
        assert f"machine PVs 01G-QSS4:* is in use by PID {proc.pid}" in capsys.readouterr().err
        assert not (tmp_path / "other.jsonl").exists()
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=10)
    crashed = read_log(log_path)
    assert crashed.last_end is None  # killed: no end record
    now = probe.read_many(ioc.setpoint_pvs[:2])
    commanded = [i["x"] for i in crashed.intents[-2:]]
    assert now.tolist() in commanded  # killed after the last intent's write, or just before it
    assert crashed.initial_knobs == start.tolist()
    n = crashed.n_evaluations
    resumed = write_config(tmp_path, ioc, ring, name="resume.yaml", budget=100_000)
    with open(resumed) as f:
        data = yaml.safe_load(f)
    data["budget"] = n + 2
    with open(resumed, "w") as f:
        yaml.safe_dump(data, f)
    assert cli.main(["optimize", "--resume", str(log_path), "--config", resumed, "--quiet"]) == 0
    captured = capsys.readouterr()
    assert "took over the stale lock" in captured.err
    assert "the knobs now against the initial knobs of the first start" in captured.out
    assert "knobs restored to initial" in captured.out
    after = probe.read_many(ioc.setpoint_pvs[:2])
    assert torch.allclose(after, start, rtol=0, atol=1e-12), (after, start, now)
    log = read_log(log_path)
    assert log.last_end["restored"] is True and log.n_evaluations == n + 2
    assert log.starts[-1]["found_knobs"] == pytest.approx(now.tolist(), abs=1e-12)


def machine(handle, ring, **options):
    b = ring.bounds  # all knobs of the shared IOC
    return EpicsMachine(handle.knob_names, b, handle.loss_rate_pv, **{**FAST, **options})


def run_nm(m, ring, callback, log, budget=6):
    optimizer = NelderMead(ring.bounds, initial_simplex_size=0.05)
    return optimize(m, optimizer, budget=budget, callback=callback, log=log)


def test_an_ioc_reboot_during_an_averaged_reading_discards_it(ioc, probe, ring, tmp_path):
    """The IOC reboots (every knob back to 0) in the middle of step 2's averaged reading: the
    reading is discarded and logged as such, never becomes an evaluation or the best, and the
    run aborts with MachineError after putting the initial knobs back."""
    d = len(ioc.knob_names)
    start = ring.bounds[1] * 0.1
    probe.write_many(ioc.setpoint_pvs, start)

    def callback(row):
        if row["step"] == 1:
            probe.write(ioc.reboot_on_read_pv, 2)  # the 2nd of step 2's 3 readings

    log = tmp_path / "r.jsonl"
    with machine(ioc, ring, n_average=3, average_interval=0.06) as m:
        with pytest.raises(MachineError, match="reading discarded and the knobs moved"):
            run_nm(m, ring, callback, log)
    records = read_log(log)
    assert records.n_evaluations == 2 and [r["step"] for r in records.discarded] == [2]
    assert "readbacks of knobs" in records.discarded[0]["reason"]
    end = records.last_end
    assert end["status"] == "aborted" and end["restored"] is True
    assert torch.equal(probe.read_many(ioc.setpoint_pvs), start) and d == len(start)


def test_a_frozen_objective_pv_stops_the_run(ioc, probe, ring, tmp_path):
    """The loss-rate PV stops updating after step 1: no reading is accepted twice; the run ends
    with a ReadError of stale readings (after the loop's retries) instead of 'completed', knobs
    restored;
    the accepted readings carry strictly increasing CA timestamps."""

    def callback(row):
        if row["step"] == 1:
            probe.write(ioc.frozen_pv, 1)

    log = tmp_path / "r.jsonl"
    with machine(ioc, ring, stale_timeout=0.3) as m:
        t0 = time.monotonic()
        with pytest.raises(ReadError, match=r"StaleReadingError: .* has not updated for 0\.3 s"):
            run_nm(m, ring, callback, log, budget=12)
        assert time.monotonic() - t0 < 20
    records = read_log(log)
    # a refresh published between step 1's reading and the freeze may still serve step 2
    assert records.n_evaluations in (2, 3) and records.last_end["status"] == "aborted"
    stamps = [s for e in records.evaluations for s in e["reading"]["stamps"]]
    assert len(stamps) == records.n_evaluations
    assert all(b > a for a, b in itertools.pairwise(stamps))
    assert torch.equal(probe.read_many(ioc.setpoint_pvs), torch.zeros(len(ioc.knob_names)))


def test_a_restore_that_fails_exits_3_with_the_last_setpoint(
    ioc, probe, ring, tmp_path, capsys, with_optimize
):
    """The knobs stop following their setpoints mid-run (readbacks 5 s late): the run aborts,
    every restore attempt fails; exit 3 (not 1), the last setpoint written is printed and in the
    end record, with restored false."""
    machine = {"kind": "epics", "settle_time": 0.1, "timeout": 0.4, "stale_timeout": 1.0}
    config = write_config(tmp_path, ioc, ring, restore_attempts=2, budget=8, machine=machine)
    probe.write_many(ioc.setpoint_pvs[:2], start_of(ring))
    calls = {"n": 0}
    real = EpicsMachine.read

    def read(self):
        calls["n"] += 1
        if calls["n"] == 5 + 3:  # after the noise measurement's 5 readings and evaluation 1
            probe.write(ioc.readback_delay_pv, 5.0)
        return real(self)

    EpicsMachine.read = read
    try:
        with pytest.warns(UserWarning, match=r"could not restore .* last setpoint acknowledged"):
            code = cli.main(["optimize", "--config", config, "--quiet"])
    finally:
        EpicsMachine.read = real
    captured = capsys.readouterr()
    assert code == 3, captured.err
    assert "KNOBS NOT RESTORED" in captured.out and "last setpoint acknowledged:" in captured.out
    assert "exit status 3" in captured.err
    log = read_log(tmp_path / "run.jsonl")
    end = log.last_end
    assert end["restored"] is False and end["restore_attempts"] == 2
    assert end["last_setpoint"] == log.last_intent["x"]  # the restore ramp's last write
    assert log.last_intent["purpose"] == "restore initial"
    last = ", ".join(f"{n}={v:.6g}" for n, v in zip(KNOBS, end["last_setpoint"], strict=True))
    assert f"last setpoint acknowledged: {last}" in captured.out
    # setpoint space: the setpoints are back at the start although a readback never followed
    assert torch.equal(probe.read_many(ioc.setpoint_pvs[:2]), start_of(ring))
    assert end["final_setpoints"] == start_of(ring).tolist() == end["restore_target"]


def test_a_missing_pv_is_one_message_without_traceback(ioc, ring, tmp_path, capsys, with_optimize):
    """An objective PV that no IOC serves: exit 1, one line naming the PV, no traceback."""
    config = write_config(tmp_path, ioc, ring, objective={"pv": "NO:SUCH:PV"})
    assert cli.main(["optimize", "--config", config]) == 1
    err = capsys.readouterr().err
    assert "could not connect to the machine" in err and "NO:SUCH:PV" in err
    assert "Traceback" not in err
