"""The run log's faults over real Channel Access (the shared simulated IOC on 127.0.0.1): a full
log disk at the start, mid-run, and together with a supply whose readback stops following; an
edited or torn log on resume; a run file with max_step 1000. Each test reads what the IOC ended
with, through a CA client of its own, and — where nothing may be written — the setpoint PVs' CA
timestamps, which any put would have advanced.

Runs go through `pigp optimize` in this process; the disk is filled by standing in for ``os``
in the run-log writer (ENOSPC from the n-th record on), which works in CI without mounting
anything.
"""

from __future__ import annotations

import json
import os

import pytest
import torch
import yaml

import pigp_torch.data.runlog.writer as writer_module
from pigp_torch import cli
from pigp_torch.data.runlog import read_log
from tests.commands.test_log_faults import DiskFull, downgrade

from .ca_runs import KNOBS, bounds_of, start_of, write_config


@pytest.fixture(autouse=True)
def private_locks(tmp_path, monkeypatch):
    """Machine locks in this test's folder (not the host's shared one)."""
    monkeypatch.setenv("PIGP_LOCK_DIR", str(tmp_path / "locks"))


def setpoints(ioc, probe) -> torch.Tensor:
    return probe.read_many(ioc.setpoint_pvs[:2])


def put_stamps(ioc, probe) -> list[float]:
    """CA timestamps of the two setpoint PVs (a put advances them, even to the same value)."""
    return [
        probe.pv(n).read(data_type="time", timeout=probe.timeout).metadata.timestamp
        for n in ioc.setpoint_pvs[:2]
    ]


def test_a_full_disk_at_the_start_puts_nothing(ioc, probe, ring, tmp_path, capsys, monkeypatch):
    """The header cannot be written: exit 1 in one line, no log left, and the IOC received no
    put (setpoints and their timestamps unchanged)."""
    start = start_of(ring)
    probe.write_many(ioc.setpoint_pvs[:2], start)
    stamps = put_stamps(ioc, probe)
    monkeypatch.setattr(writer_module, "os", DiskFull(0))
    assert cli.main(["optimize", "--config", write_config(tmp_path, ioc, ring), "--quiet"]) == 1
    err = capsys.readouterr().err
    assert "could not start the run" in err and "No space left on device" in err
    assert not (tmp_path / "run.jsonl").exists()
    assert torch.equal(setpoints(ioc, probe), start) and put_stamps(ioc, probe) == stamps
    probe.write_many(ioc.setpoint_pvs[:2], start)  # the check can fail: a put of the same
    assert all(b > a for a, b in zip(stamps, put_stamps(ioc, probe), strict=True))  # values


def test_a_full_disk_mid_run_restores_the_ioc_exactly(
    ioc, probe, ring, tmp_path, capsys, monkeypatch, run_mode
):
    """The disk fills after 12 records: exit 1, one line naming the reason, the summary, and the
    IOC's setpoints back at their initial values bit for bit (in a track run too)."""
    start = start_of(ring)
    probe.write_many(ioc.setpoint_pvs[:2], start)
    monkeypatch.setattr(writer_module, "os", DiskFull(12))
    config = write_config(tmp_path, ioc, ring, budget=40, **run_mode)
    assert cli.main(["optimize", "--config", config, "--quiet"]) == 1
    captured = capsys.readouterr()
    assert "pigp optimize: run stopped: could not write to the run log" in captured.err
    assert len(captured.err.splitlines()) == 1  # one line, not one per record refused
    assert "knobs restored to initial" in captured.out and "status: failed" in captured.out
    assert torch.equal(setpoints(ioc, probe), start)
    monkeypatch.setattr(writer_module, "os", os)
    log = read_log(tmp_path / "run.jsonl")
    assert log.n_evaluations >= 1 and log.last_end is None


def test_a_full_disk_and_a_supply_that_stops_following_exit_3(
    ioc, probe, ring, tmp_path, capsys, monkeypatch, run_mode
):
    """At the moment the disk fills the readbacks start lagging 5 s behind their setpoints (a
    supply that stops following): the restore cannot be verified and the end record cannot be
    written; exit 3, KNOBS NOT RESTORED, and the last setpoint printed is what the IOC holds."""
    start = start_of(ring)
    probe.write_many(ioc.setpoint_pvs[:2], start)
    monkeypatch.setattr(
        writer_module, "os", DiskFull(12, on_full=lambda: probe.write(ioc.readback_delay_pv, 5.0))
    )
    machine = {"kind": "epics", "settle_time": 0.1, "timeout": 0.4, "stale_timeout": 1.0}
    config = write_config(tmp_path, ioc, ring, budget=40, machine=machine, restore_attempts=2,
                          **run_mode)  # fmt: skip
    assert cli.main(["optimize", "--config", config, "--quiet"]) == 3
    captured = capsys.readouterr()
    assert "the knobs were NOT restored (exit status 3)" in captured.err
    assert "KNOBS NOT RESTORED" in captured.out and "the end record is NOT in it" in captured.out
    now = setpoints(ioc, probe)
    held = ", ".join(f"{n}={v:.6g}" for n, v in zip(KNOBS, now.tolist(), strict=True))
    assert f"last setpoint acknowledged: {held}" in captured.out


def edit_first(path, kind, change) -> int:
    lines = path.read_text().splitlines(keepends=True)
    k = next(i for i, ln in enumerate(lines) if f'"type":"{kind}"' in ln)
    record = json.loads(lines[k])
    change(record)
    lines[k] = json.dumps(record, separators=(",", ":")) + "\n"
    path.write_text("".join(lines))
    return k + 1


def test_an_edited_initial_knob_is_refused_and_nothing_is_put(
    ioc, probe, ring, tmp_path, capsys, run_mode
):
    """A finished run's first start record edited to initial knobs at the upper bounds (the
    restore target): --resume exits 2 naming that line; the IOC receives no put (a track run
    too, here ending at its initial knobs)."""
    start = start_of(ring)
    probe.write_many(ioc.setpoint_pvs[:2], start)
    run_mode["restore"] = "initial"
    config = write_config(tmp_path, ioc, ring, budget=4, **run_mode)
    assert cli.main(["optimize", "--config", config, "--quiet"]) == 0
    assert torch.equal(setpoints(ioc, probe), start)
    log = tmp_path / "run.jsonl"
    upper = bounds_of(ring)[1].tolist()
    line = edit_first(log, "start", lambda r: r.update(initial_knobs=upper))
    capsys.readouterr()
    stamps = put_stamps(ioc, probe)
    more = write_config(tmp_path, ioc, ring, name="more.yaml", budget=8, **run_mode)
    assert cli.main(["optimize", "--resume", str(log), "--config", more, "--quiet"]) == 2
    assert f"run.jsonl:{line}: the record does not match the log's hash chain" in (
        capsys.readouterr().err
    )
    assert torch.equal(setpoints(ioc, probe), start) and put_stamps(ioc, probe) == stamps


def default_window(path: str) -> str:
    """The run file without its restore_timeout (the default, as a version-2 run file had)."""
    data = yaml.safe_load(open(path))
    data.pop("restore_timeout")
    with open(path, "w") as f:
        yaml.safe_dump(data, f)
    return path


@pytest.mark.parametrize("as_written", [False, True])
def test_a_downgraded_and_edited_log_puts_nothing(ioc, probe, ring, tmp_path, capsys, as_written):
    """A finished run's log set to version 2 with every hash deleted and its first start's
    initial knobs edited to the upper bounds: refused (exit 2) with no put at the IOC, whether
    the log still holds what only newer versions write (refused as edited) or was stripped to
    what version 2 wrote (its unverifiable restore target is shown and refused: more than
    max_step from the setpoints now)."""
    start = start_of(ring)
    probe.write_many(ioc.setpoint_pvs[:2], start)
    config, more = (default_window(write_config(tmp_path, ioc, ring, name=name, budget=budget))
                    for name, budget in (("run.yaml", 4), ("more.yaml", 8)))  # fmt: skip
    assert cli.main(["optimize", "--config", config]) == 0
    log = tmp_path / "run.jsonl"
    upper = bounds_of(ring)[1].tolist()
    downgrade(log, as_written=as_written, change=lambda r: r.update(initial_knobs=upper))
    capsys.readouterr()
    stamps, mark = put_stamps(ioc, probe), ioc.n_puts()
    assert cli.main(["optimize", "--resume", str(log), "--config", more, "--quiet"]) == 2
    err = capsys.readouterr().err
    if as_written:
        assert "its restore target (the initial knobs above) cannot be verified" in err
    else:
        assert "run.jsonl:1: the log claims run-log version 2 (no hash chain) but" in err
    assert torch.equal(setpoints(ioc, probe), start) and put_stamps(ioc, probe) == stamps
    assert ioc.puts(mark) == []


@pytest.mark.slow
def test_a_torn_last_line_resumes_over_ca(ioc, probe, ring, tmp_path, capsys):
    """A log whose last line a crash cut in two resumes to the budget and restores the IOC to
    the first start's knobs exactly."""
    start = start_of(ring)
    probe.write_many(ioc.setpoint_pvs[:2], start)
    config = write_config(tmp_path, ioc, ring, budget=4)
    assert cli.main(["optimize", "--config", config, "--quiet"]) == 0
    log = tmp_path / "run.jsonl"
    text = log.read_text()
    log.write_text(text[: len(text) - 40])  # the end record cut mid-write
    more = write_config(tmp_path, ioc, ring, name="more.yaml", budget=7)
    assert cli.main(["optimize", "--resume", str(log), "--config", more, "--quiet"]) == 0
    assert "cut short by an interrupted write" in capsys.readouterr().err
    assert torch.equal(setpoints(ioc, probe), start)
    assert read_log(log).n_evaluations == 7


def test_max_step_1000_is_refused_before_any_put(ioc, probe, ring, tmp_path, capsys):
    """max_step: 1000 (a thousand half-ranges per set): exit 2, one line, no connection needed
    and no put reaches the IOC."""
    start = start_of(ring)
    probe.write_many(ioc.setpoint_pvs[:2], start)
    stamps = put_stamps(ioc, probe)
    assert cli.main(["optimize", "--config", write_config(tmp_path, ioc, ring, max_step=1000)]) == 2
    err = capsys.readouterr().err
    assert "max_step 1000 is above 1" in err and "max_step: unlimited" in err
    assert torch.equal(setpoints(ioc, probe), start) and put_stamps(ioc, probe) == stamps
    assert not (tmp_path / "run.jsonl").exists()
