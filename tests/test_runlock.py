"""Run locks: one writer per run log, one run per machine (PV prefix), stale locks taken over."""

from __future__ import annotations

import json
import subprocess
import sys
import time

import pytest

from pigp_torch.data.runlock import LockHeld, RunLock, holding, log_lock, machine_locks, pv_prefixes
from pigp_torch.data.runlog import RunLog, read_log


def test_a_second_writer_of_a_log_is_refused_and_the_log_stays_intact(tmp_path):
    """While one RunLog is open on a path, create/append from anywhere are refused with the
    holder named; after close the log continues normally and holds every record once."""
    path = tmp_path / "run.jsonl"
    first = RunLog.create(path, {"knob_names": ["a"]})
    first.log_evaluation(0, [0.5], 1.0)
    with pytest.raises(LockHeld, match=r"run log .*run.jsonl is in use by PID \d+"):
        RunLog.append(path)
    first.log_evaluation(1, [0.25], 2.0)
    first.close()
    assert not (tmp_path / "run.jsonl.lock").exists()
    with RunLog.append(path) as again:
        again.log_evaluation(2, [0.125], 3.0)
    assert [e["step"] for e in read_log(path).evaluations] == [0, 1, 2]


def test_a_lock_held_by_another_process_is_refused_and_a_dead_ones_is_stale(tmp_path):
    """A child process holds the lock: LockHeld names its PID. After the child is killed (no
    clean-up), the lock is free again and its leftover description is reported as stale."""
    path = tmp_path / "x.lock"
    code = (
        "import sys, time; from pigp_torch.data.runlock import RunLock; "
        f"RunLock({str(path)!r}, 'test').acquire(); print('held', flush=True); time.sleep(60)"
    )
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "held"
        with pytest.raises(LockHeld) as info:
            RunLock(path, "test").acquire()
        assert info.value.holder["pid"] == proc.pid
        assert f"PID {proc.pid}" in str(info.value)
    finally:
        proc.kill()
        proc.wait(timeout=10)
    assert json.loads(path.read_text())["pid"] == proc.pid  # left behind by the kill
    deadline = time.monotonic() + 5
    lock = RunLock(path, "test")
    while True:  # the kernel frees the flock when the process is reaped
        try:
            lock.acquire()
            break
        except LockHeld:
            assert time.monotonic() < deadline
            time.sleep(0.05)
    assert lock.stale["pid"] == proc.pid and lock.stale["alive"] is False
    lock.release()
    assert not path.exists()


def test_machine_locks_are_per_pv_prefix(tmp_path):
    """Runs whose PVs share a prefix (here the objective's) exclude each other; disjoint ones
    do not; taking a set is all or nothing."""
    assert pv_prefixes(["01G-QSS4:CurrSetpt", "01G-QSS4:Curr1", "SPEAR:BeamLossRate"]) == [
        "01G-QSS4",
        "SPEAR",
    ]
    a = machine_locks(["01G-QSS4:CurrSetpt", "SPEAR:BeamLossRate"], tmp_path)
    b = machine_locks(["02G-QSS3:CurrSetpt", "SPEAR:BeamLossRate"], tmp_path)
    c = machine_locks(["02G-QSS3:CurrSetpt", "BOOSTER:Loss"], tmp_path)
    with holding(a):
        with pytest.raises(LockHeld, match=r"machine PVs SPEAR:\* is in use"):
            with holding(b):
                pass  # pragma: no cover - never reached
        assert not b[0].held  # the 02G-QSS3 lock taken before the refusal was released
        with holding(c) as taken:
            assert [lock.held for lock in taken] == [True, True]
    assert log_lock(tmp_path / "r.jsonl").path.name == "r.jsonl.lock"
