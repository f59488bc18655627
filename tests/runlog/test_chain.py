"""Tests of the run log's hash chain and of writes that fail: every record's hash is the sha256
of the previous hash and the record's canonical JSON; an edit, insertion, deletion or swap is
refused at the first line that does not match; a failed write leaves nothing of its record and
keeps the chain in step with the file, whatever interrupts it."""

from __future__ import annotations

import errno
import hashlib
import json
import os
import warnings

import pytest

import pigp_torch.data.runlog.writer as writer_module
from pigp_torch.data.runlog import (
    LogWriteError,
    RunLog,
    TornLineWarning,
    UnchainedLogWarning,
    read_log,
)


def make_log(path, n=3) -> None:
    with RunLog.create(path, {"knob_names": ["a", "b"], "bounds": [[-1, -1], [1, 1]]}) as log:
        log.log_start([0.1, -0.2], budget=n, first_step=0)
        for k in range(n):
            log.log_intent([0.1 * k, 0.0], purpose="evaluation", step=k)
            log.log_evaluation(k, [0.1 * k, 0.0], 1.0 - k / 7, reads=1)
        log.log_end("completed", restored_to="initial", final_knobs=[0.1, -0.2])


def test_each_hash_is_sha256_of_the_previous_hash_and_the_canonical_record(tmp_path):
    """Recomputed here with hashlib from the file's text: h_k = sha256(h_{k-1} + c_k), h_{-1} =
    "" — the header starts the chain."""
    path = tmp_path / "r.jsonl"
    make_log(path)
    previous = ""
    lines = path.read_text().splitlines()
    for line in lines:
        record = json.loads(line)
        logged = record.pop("hash")
        canonical = json.dumps(record, sort_keys=True, separators=(",", ":"))
        assert logged == hashlib.sha256((previous + canonical).encode()).hexdigest()
        previous = logged
    records = read_log(path)
    assert records.chained and records.verified and records.last_hash == previous
    assert len(lines) == 9 and records.header["version"] == 3


def rewrite(path, lines) -> None:
    path.write_text("".join(line + "\n" for line in lines))


@pytest.mark.parametrize(
    ("line", "change"),
    [
        (1, lambda r: r.update(bounds=[[-2, -2], [2, 2]])),
        (2, lambda r: r.update(initial_knobs=[0.9, 0.9])),
        (4, lambda r: r.update(y=1e6)),
        (5, lambda r: r.update(x=[0.1000000001, 0.0])),
        (9, lambda r: r.update(restored_to="best")),
        (7, lambda r: r.pop("hash")),
    ],
    ids=["header-bounds", "initial_knobs", "reading", "intent-x", "end", "hash-removed"],
)
def test_an_edited_record_is_refused_at_its_line(tmp_path, line, change):
    """Any field of any record, the header included, or a removed hash: ValueError naming the
    line; verify=False still reads the edited log (for inspection)."""
    path = tmp_path / "r.jsonl"
    make_log(path)
    lines = path.read_text().splitlines()
    record = json.loads(lines[line - 1])
    change(record)
    lines[line - 1] = json.dumps(record, separators=(",", ":"))
    rewrite(path, lines)
    with pytest.raises(ValueError, match=rf"r.jsonl:{line}: the record (does not match|has no)"):
        read_log(path)
    assert read_log(path, verify=False).n_evaluations == 3


def test_removed_inserted_and_swapped_lines_are_refused(tmp_path):
    """A line removed from the middle (refused at the line after the gap), a line copied in, two
    lines swapped: each refused at the first line out of place. Cutting the log at a record
    boundary is a valid prefix (as after a crash between two records)."""
    path = tmp_path / "r.jsonl"
    make_log(path)
    lines = path.read_text().splitlines()
    rewrite(path, lines[:4] + lines[5:])
    with pytest.raises(ValueError, match=r"r.jsonl:5: the record does not match"):
        read_log(path)
    rewrite(path, [*lines[:6], lines[3], *lines[6:]])
    with pytest.raises(ValueError, match=r"r.jsonl:7: the record does not match"):
        read_log(path)
    rewrite(path, [*lines[:2], lines[3], lines[2], *lines[4:]])
    with pytest.raises(ValueError, match=r"r.jsonl:3: the record does not match"):
        read_log(path)
    rewrite(path, lines[:7])
    assert read_log(path).n_evaluations == 2


def test_a_downgraded_header_is_refused(tmp_path):
    """A chained header relabelled version 2 (to skip verification) is refused at line 1."""
    path = tmp_path / "r.jsonl"
    make_log(path)
    lines = path.read_text().splitlines()
    lines[0] = lines[0].replace('"version":3', '"version":2')
    rewrite(path, lines)
    with pytest.raises(ValueError, match=r"r.jsonl:1: the header carries a hash but claims"):
        read_log(path)


def test_a_torn_last_line_is_one_warning_and_appending_continues_the_chain(tmp_path):
    """The cut line is dropped with one TornLineWarning per read (none with warn=False, the line
    is in .warnings either way); append() cuts it off and the chain goes on."""
    path = tmp_path / "r.jsonl"
    make_log(path)
    with open(path, "a") as f:
        f.write('{"type":"evaluation","step":3,"x":[0.')
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        records = read_log(path)
    assert [w.category for w in seen] == [TornLineWarning] and records.torn_line == 10
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        quiet = read_log(path, warn=False)
    assert quiet.warnings == [str(seen[0].message)] and quiet.n_evaluations == 3
    with RunLog.append(path, warn=False) as log:
        log.log_start([0.1, -0.2], budget=4, first_step=3)
    records = read_log(path)
    assert records.verified and records.torn_line is None and len(records.starts) == 2


def test_an_old_log_without_a_chain_is_read_and_appended_unchained(tmp_path):
    """A version-2 log (no hashes): read with one UnchainedLogWarning; records appended to it
    stay without a hash (the log remains what it was: unverifiable)."""
    path = tmp_path / "r.jsonl"
    make_log(path)
    lines = []
    for line in path.read_text().splitlines():
        record = json.loads(line)
        record.pop("hash")
        record.update(version=2) if record["type"] == "header" else None
        lines.append(json.dumps(record))
    rewrite(path, lines)
    with pytest.warns(UnchainedLogWarning, match="cannot be verified"):
        records = read_log(path)
    assert not records.chained and not records.verified and records.last_hash is None
    with RunLog.append(path, warn=False) as log:
        log.log_start([0.1, -0.2], budget=4, first_step=3)
    assert "hash" not in json.loads(path.read_text().splitlines()[-1])


class FlakyOS:
    """``os`` for the writer with scripted failures: ``write_plan`` / ``fsync_plan`` map the
    call number (from 1) to an exception to raise, or to ``"half"`` (write half the bytes)."""

    def __init__(self, write_plan=None, fsync_plan=None, truncate_error=None) -> None:
        self.write_plan, self.fsync_plan = write_plan or {}, fsync_plan or {}
        self.truncate_error = truncate_error
        self.writes = self.fsyncs = 0

    def write(self, fd, data):
        self.writes += 1
        action = self.write_plan.get(self.writes)
        if action == "half":
            return os.write(fd, bytes(data[: len(data) // 2]))
        if action is not None:
            raise action
        return os.write(fd, data)

    def fsync(self, fd):
        self.fsyncs += 1
        action = self.fsync_plan.get(self.fsyncs)
        if action is not None:
            raise action
        return os.fsync(fd)

    def ftruncate(self, fd, size):
        if self.truncate_error is not None:
            raise self.truncate_error
        return os.ftruncate(fd, size)

    def __getattr__(self, name):
        return getattr(os, name)


ENOSPC = OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


def test_a_failed_write_leaves_nothing_and_a_later_one_continues_the_chain(tmp_path, monkeypatch):
    """Half a record written then ENOSPC, and an fsync that fails (EIO): LogWriteError each time,
    the file cut back to its complete records; once the disk works again the next records are
    written and the whole chain verifies."""
    path = tmp_path / "r.jsonl"
    log = RunLog.create(path, {"knob_names": ["a"]})
    size = path.stat().st_size
    eio = OSError(errno.EIO, os.strerror(errno.EIO))
    flaky = FlakyOS(write_plan={1: "half", 2: ENOSPC}, fsync_plan={2: eio})
    monkeypatch.setattr(writer_module, "os", flaky)
    with pytest.raises(LogWriteError, match=r"r\.jsonl: No space left on device"):
        log.log_evaluation(0, [0.5], 1.0)
    assert path.stat().st_size == size and log.write_error == "No space left on device"
    log.log_evaluation(0, [0.5], 1.0)  # write 3 and fsync 1: fine
    grown = path.stat().st_size
    with pytest.raises(LogWriteError, match="Input/output error"):
        log.log_evaluation(1, [0.25], 2.0)  # fsync 2 fails
    assert path.stat().st_size == grown
    log.log_evaluation(1, [0.25], 2.0)
    log.close()
    records = read_log(path)
    assert records.verified and [e["y"] for e in records.evaluations] == [1.0, 2.0]


def test_a_failure_that_cannot_be_undone_refuses_every_later_write(tmp_path, monkeypatch):
    """Half a record written, the write fails and the file cannot be cut back: every later
    write is refused, so the partial line stays last and readers drop it as torn."""
    path = tmp_path / "r.jsonl"
    log = RunLog.create(path, {"knob_names": ["a"]})
    log.log_evaluation(0, [0.5], 1.0)
    flaky = FlakyOS(write_plan={1: "half", 2: ENOSPC}, truncate_error=ENOSPC)
    monkeypatch.setattr(writer_module, "os", flaky)
    with pytest.raises(LogWriteError):
        log.log_evaluation(1, [0.25], 2.0)
    with pytest.raises(LogWriteError, match="an earlier write failed and left a partial record"):
        log.log_end("failed", "disk full", restored=True)
    assert log.end_record["restored"] is True and not log.end_written  # still known in memory
    log.close()
    records = read_log(path, warn=False)
    assert records.verified and records.n_evaluations == 1 and records.torn_line == 3


def test_a_signal_during_a_write_keeps_the_chain_in_step_with_the_file(tmp_path, monkeypatch):
    """A KeyboardInterrupt (a signal's exception) after the bytes reached the file (during the
    fsync) keeps the record and moves the chain on; one before any byte was written leaves
    nothing. Either way the next record verifies."""
    path = tmp_path / "r.jsonl"
    log = RunLog.create(path, {"knob_names": ["a"]})
    flaky = FlakyOS(write_plan={2: KeyboardInterrupt()}, fsync_plan={1: KeyboardInterrupt()})
    monkeypatch.setattr(writer_module, "os", flaky)
    with pytest.raises(KeyboardInterrupt):
        log.log_intent([0.5], purpose="evaluation", step=0)  # written, fsync interrupted
    with pytest.raises(KeyboardInterrupt):
        log.log_evaluation(0, [0.5], 1.0)  # interrupted before writing
    log.log_evaluation(0, [0.5], 1.0)
    log.close()
    records = read_log(path)
    assert records.verified and len(records.intents) == 1 and records.n_evaluations == 1


def test_a_header_that_cannot_be_written_removes_the_new_file_and_its_lock(tmp_path, monkeypatch):
    """ENOSPC on the header: LogWriteError, and neither the log nor its lock file is left."""
    path = tmp_path / "r.jsonl"
    monkeypatch.setattr(writer_module, "os", FlakyOS(write_plan={1: ENOSPC}))
    with pytest.raises(LogWriteError, match="No space left on device"):
        RunLog.create(path, {"knob_names": ["a"]})
    assert not path.exists() and not (tmp_path / "r.jsonl.lock").exists()


def test_reserved_hash_field_is_refused(tmp_path):
    """A caller cannot supply its own 'hash' (header or record)."""
    with pytest.raises(ValueError, match="reserved"):
        RunLog.create(tmp_path / "r.jsonl", {"hash": "0" * 64})
    with RunLog.create(tmp_path / "r.jsonl", {"knob_names": ["a"]}) as log:
        with pytest.raises(ValueError, match="reserved for the hash chain"):
            log.write("notice", hash="x")
