"""`pigp optimize` when the run log fails or is edited, and run files that must be refused, on
the simulated machine: a full log disk at the start and mid-run (injected, and on a real 64 KiB
tmpfs where mounting is permitted), a full disk together with a stuck readback, an edited or torn
log on resume, an old log without a hash chain, `pigp report` on an edited log, max_step above
1, booleans and strings for numbers, a folder as the run file, a log held by a running run, and
a dry run next to an existing log."""

from __future__ import annotations

import errno
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
import yaml

import pigp_torch.data.runlog.writer as writer_module
import pigp_torch.loop.run as run_module
from pigp_torch import cli
from pigp_torch.data.runlog import read_log
from pigp_torch.data.runlog.legacy import LEGACY_CONFIG, LEGACY_FIELDS
from pigp_torch.loop.config.schema import config_digest
from pigp_torch.machine import SimulatedMachine

KNOBS = ["01G-QSS4", "02G-QSS3"]
X_INIT = {"01G-QSS4": 0.002, "02G-QSS3": -0.001}


class DiskFull:
    """Stands in for ``os`` in the run-log writer: every ``os.write`` after the first ``n``
    raises ENOSPC (as a full disk does); ``on_full`` is called at the first failure."""

    def __init__(self, n: int, on_full=None) -> None:
        self.n, self.calls, self.on_full = n, 0, on_full

    def write(self, fd, data):
        self.calls += 1
        if self.calls > self.n:
            if self.calls == self.n + 1 and self.on_full is not None:
                self.on_full()
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return os.write(fd, data)

    def __getattr__(self, name):
        return getattr(os, name)


def write_config(tmp_path, name="run.yaml", **over) -> str:
    data = {
        "machine": {"kind": "sim", "error_seed": 1, "noise": 0.04, "seed": 2, "x_init": X_INIT},
        "knobs": {k: [-0.01, 0.01] for k in KNOBS},
        "method": {"name": "nelder-mead", "options": {"initial_simplex_size": 0.2}},
        "budget": 12,
        "max_step": 0.1,
        "log": "run.jsonl",
        "restore_interval": 0.0,
    }
    data.update(over)
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data))
    return str(path)


@pytest.fixture
def machines(monkeypatch):
    """The machines `pigp optimize` builds, kept for the test to read their knobs."""
    made = []
    real = run_module.build_run

    def build_run(config):
        setup = real(config)
        made.append(setup.machine)
        return setup

    monkeypatch.setattr(run_module, "build_run", build_run)
    return made


def initial() -> torch.Tensor:
    return torch.tensor(list(X_INIT.values()), dtype=torch.float64)


# ----------------------------------------------------------------------------- a full disk
def test_a_full_disk_at_the_start_leaves_no_log_and_moves_nothing(
    tmp_path, capsys, monkeypatch, machines
):
    """The header cannot be written: exit 1, one line, no log and no lock file left behind, the
    knobs never set; the next start (disk free again) is not refused."""
    monkeypatch.setattr(writer_module, "os", DiskFull(0))
    sets = []
    real_set = SimulatedMachine.set
    monkeypatch.setattr(SimulatedMachine, "set", lambda m, x: (sets.append(x), real_set(m, x)))
    config = write_config(tmp_path)
    assert cli.main(["optimize", "--config", config, "--quiet"]) == 1
    err = capsys.readouterr().err
    assert "could not start the run: could not write to the run log" in err
    assert "No space left on device" in err and "nothing was moved" in err
    assert not (tmp_path / "run.jsonl").exists() and not (tmp_path / "run.jsonl.lock").exists()
    assert sets == [] and torch.equal(machines[0].get(), initial())
    monkeypatch.setattr(writer_module, "os", os)
    assert cli.main(["optimize", "--config", config, "--quiet"]) == 0
    assert read_log(tmp_path / "run.jsonl").n_evaluations == 12


def test_a_full_disk_mid_run_restores_the_knobs_and_prints_the_summary(
    tmp_path, capsys, monkeypatch, machines
):
    """The disk fills after 12 records: the run stops (exit 1) with one line naming the log and
    the reason, the knobs are back exactly at their initial values, the summary is printed from
    the end record kept in memory, and the log on disk is consistent (chain verified, no partial
    line)."""
    disk = DiskFull(12)
    monkeypatch.setattr(writer_module, "os", disk)
    config = write_config(tmp_path, budget=40)
    assert cli.main(["optimize", "--config", config, "--quiet"]) == 1
    captured = capsys.readouterr()
    assert "pigp optimize: run stopped: could not write to the run log" in captured.err
    assert "No space left on device" in captured.err and "Traceback" not in captured.err
    assert len(captured.err.splitlines()) == 1  # the rule: one line (no repeats per record)
    assert "status: failed (LogWriteError" in captured.out
    assert "knobs restored to initial" in captured.out
    assert "a write failed: No space left on device; the end record is NOT in it" in captured.out
    assert torch.equal(machines[0].get(), initial())
    monkeypatch.setattr(writer_module, "os", os)
    log = read_log(tmp_path / "run.jsonl")  # verified: the chain matches every line
    assert len((tmp_path / "run.jsonl").read_text().splitlines()) == 12
    assert log.last_end is None and 0 < log.n_evaluations < 40
    assert not (tmp_path / "run.jsonl.lock").exists()


def test_a_read_only_log_folder_exits_1_like_a_full_disk(tmp_path, capsys, monkeypatch):
    """A log folder that cannot be written: exit 1 (the log cannot be started, as on a full
    disk), one line, nothing moved and no log."""
    real = os.access
    monkeypatch.setattr(os, "access", lambda p, mode: False if str(p) == str(tmp_path) else
                        real(p, mode))  # fmt: skip
    assert cli.main(["optimize", "--config", write_config(tmp_path), "--quiet"]) == 1
    err = capsys.readouterr().err
    assert err.splitlines() == [
        f"pigp optimize: could not start the run: the run log {tmp_path / 'run.jsonl'} cannot be "
        f"created: {tmp_path} is not writable; nothing was moved"
    ]
    assert not (tmp_path / "run.jsonl").exists()


@pytest.mark.parametrize("value", [".nan", ".inf", "-.inf"])
def test_a_non_finite_max_step_is_one_line(tmp_path, capsys, value):
    """max_step NaN or infinite (YAML .nan / .inf, or 1e400 in JSON): exit 2, one line."""
    path = Path(write_config(tmp_path))
    path.write_text(path.read_text().replace("max_step: 0.1", f"max_step: {value}"))
    assert cli.main(["optimize", "--config", str(path)]) == 2
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and "is not a step limit: give a finite fraction" in lines[0]
    json_path = tmp_path / "run.json"
    json_path.write_text(
        json.dumps(yaml.safe_load(path.read_text().replace(f"max_step: {value}", "max_step: 1")))
        .replace('"max_step": 1', '"max_step": 1e400')
    )  # fmt: skip
    assert cli.main(["optimize", "--config", str(json_path)]) == 2
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and "max_step: inf is not a step limit" in lines[0]


def test_a_full_disk_and_a_stuck_readback_exit_3(tmp_path, capsys, monkeypatch, machines):
    """The disk fills and, at that moment, the knob readbacks stop following (a stuck supply):
    the restore cannot be verified, the end record cannot be written, and the exit status is
    still 3 with KNOBS NOT RESTORED and the last setpoint written printed."""
    stuck = {}
    real_get = SimulatedMachine.get

    def get(self):
        return stuck["x"].clone() if "x" in stuck else real_get(self)

    def freeze():
        stuck["x"] = real_get(machines[0]) + 0.001

    monkeypatch.setattr(SimulatedMachine, "get", get)
    monkeypatch.setattr(writer_module, "os", DiskFull(12, on_full=freeze))
    config = write_config(tmp_path, budget=40, restore_attempts=2, restore_timeout=0.0)
    assert cli.main(["optimize", "--config", config, "--quiet"]) == 3
    captured = capsys.readouterr()
    assert "the knobs were NOT restored (exit status 3)" in captured.err
    assert "KNOBS NOT RESTORED (initial (failed), 2 attempt(s))" in captured.out
    assert "last setpoint acknowledged: 01G-QSS4=" in captured.out
    assert not torch.equal(get(machines[0]), initial())  # the readback is stuck off the target
    assert "the end record is NOT in it" in captured.out


def test_a_completed_run_whose_end_record_cannot_be_written_exits_1(
    tmp_path, capsys, monkeypatch, machines
):
    """Only the end record fails (the disk fills after the same run's other records, counted on
    an identical run first): the knobs are restored, the summary says completed and that the
    end record is not in the log; exit 1, not 0 (the log is incomplete)."""
    assert cli.main(["optimize", "--config", write_config(tmp_path, "a.yaml", log="a.jsonl")]) == 0
    n = len((tmp_path / "a.jsonl").read_text().splitlines())
    capsys.readouterr()
    monkeypatch.setattr(writer_module, "os", DiskFull(n - 1))
    assert cli.main(["optimize", "--config", write_config(tmp_path), "--quiet"]) == 1
    captured = capsys.readouterr()
    assert "status: completed" in captured.out and "knobs restored to initial" in captured.out
    assert "the end record is NOT in it" in captured.out and "run stopped:" in captured.err
    assert torch.equal(machines[-1].get(), initial())
    monkeypatch.setattr(writer_module, "os", os)
    log = read_log(tmp_path / "run.jsonl")
    assert log.last_end is None and log.n_evaluations == 12


CHILD = (
    "import errno, os, sys; import pigp_torch.data.runlog.writer as w; n = int(sys.argv[1])\n"
    "class Full:\n"
    "    calls = 0\n"
    "    def write(self, fd, data):\n"
    "        Full.calls += 1\n"
    "        if Full.calls > n: raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))\n"
    "        return os.write(fd, data)\n"
    "    def __getattr__(self, name): return getattr(os, name)\n"
    "w.os = Full() if n >= 0 else os\n"
    "import pigp_torch.cli as c; sys.exit(c.main(sys.argv[2:]))"
)


def run_child(args, n_writes=-1, timeout=120):
    env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}
    return subprocess.run(
        [sys.executable, "-c", CHILD, str(n_writes), *args],
        capture_output=True,
        text=True,
        env=env,
        timeout=timeout,
    )


def plain_stderr(err: str) -> list[str]:
    """stderr lines that are not the command's own one-line messages (should be none)."""
    return [ln for ln in err.splitlines() if not ln.startswith(("pigp optimize:", "warning:"))]


def test_a_full_disk_in_a_process_prints_plain_lines_only(tmp_path):
    """In a real process (the warnings as a user sees them): exit 1, stderr holds only one-line
    messages — no traceback, no Python source line — and stdout the summary."""
    proc = run_child(["optimize", "--config", write_config(tmp_path, budget=40)], n_writes=12)
    assert proc.returncode == 1, proc.stderr
    assert plain_stderr(proc.stderr) == [], proc.stderr
    assert "run stopped: could not write to the run log" in proc.stderr
    assert "knobs restored to initial, readback: 01G-QSS4=0.002, 02G-QSS3=-0.001" in proc.stdout


# ------------------------------------------------------------------- a real 64 KiB tmpfs
@pytest.fixture
def small_disk(tmp_path):
    """A 64 KiB tmpfs mounted at tmp_path/disk (root and a kernel that permits it; else skip)."""
    disk = tmp_path / "disk"
    disk.mkdir()
    try:
        proc = subprocess.run(
            ["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(disk)],
            capture_output=True,
            timeout=20,
        )
    except (OSError, subprocess.TimeoutExpired) as err:
        pytest.skip(f"cannot mount a tmpfs: {err}")
    if proc.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs: {proc.stderr.decode(errors='replace').strip()}")
    try:
        yield disk
    finally:
        subprocess.run(["umount", str(disk)], capture_output=True, timeout=20)


def fill(disk: Path, leave_pages: int) -> None:
    """Fill ``disk`` up, then free ``leave_pages`` pages of 4 KiB."""
    filler = disk / "filler"
    fd = os.open(filler, os.O_WRONLY | os.O_CREAT)
    try:
        while True:
            try:
                if os.write(fd, b"\0" * 4096) == 0:
                    break
            except OSError as err:
                assert err.errno == errno.ENOSPC
                break
        size = os.fstat(fd).st_size
        os.ftruncate(fd, max(0, size - 4096 * leave_pages))
    finally:
        os.close(fd)


def test_a_full_tmpfs_at_the_start_leaves_no_log(tmp_path, small_disk):
    """A 64 KiB tmpfs with no free page: exit 1 in one line, no empty log left behind."""
    fill(small_disk, 0)
    config = write_config(tmp_path, log="disk/run.jsonl")
    proc = run_child(["optimize", "--config", config, "--quiet"])
    assert proc.returncode == 1, proc.stderr
    assert plain_stderr(proc.stderr) == [], proc.stderr
    assert "No space left on device" in proc.stderr
    assert not (small_disk / "run.jsonl").exists()


def test_a_tmpfs_that_fills_mid_run_stops_the_run_safely(tmp_path, small_disk):
    """A 64 KiB tmpfs with two free pages (the lock file's and 4 KiB of log): the run stops
    when the log's page is full, exit 1, plain lines only, knobs restored (the summary's
    readback is the initial knobs), and the log reads back with its chain intact."""
    fill(small_disk, 2)
    config = write_config(tmp_path, log="disk/run.jsonl", budget=200)
    proc = run_child(["optimize", "--config", config, "--quiet"])
    assert proc.returncode == 1, proc.stderr
    assert plain_stderr(proc.stderr) == [], proc.stderr
    assert "run stopped: could not write to the run log" in proc.stderr
    assert "knobs restored to initial, readback: 01G-QSS4=0.002, 02G-QSS3=-0.001" in proc.stdout
    log = read_log(small_disk / "run.jsonl")
    assert log.n_evaluations < 200 and (small_disk / "run.jsonl").stat().st_size <= 4096


# ---------------------------------------------------------------------- an edited run log
def finished_run(tmp_path, budget=5, final_budget=9) -> tuple[Path, str]:
    """A completed run of ``budget`` evaluations and a run file to resume it to
    ``final_budget``."""
    assert cli.main(["optimize", "--config", write_config(tmp_path, budget=budget)]) == 0
    return tmp_path / "run.jsonl", write_config(tmp_path, "more.yaml", budget=final_budget)


def edit(path: Path, line_no: int, change) -> None:
    lines = path.read_text().splitlines(keepends=True)
    record = json.loads(lines[line_no - 1])
    change(record)
    lines[line_no - 1] = json.dumps(record, separators=(",", ":")) + "\n"
    path.write_text("".join(lines))


def line_of(path: Path, kind: str, nth: int = 0) -> int:
    lines = path.read_text().splitlines()
    return [k for k, ln in enumerate(lines, 1) if f'"type":"{kind}"' in ln][nth]


@pytest.mark.parametrize(
    ("kind", "change"),
    [
        ("start", lambda r: r.update(initial_knobs=[0.009, 0.009])),
        ("evaluation", lambda r: r.update(y=1e6)),
        ("header", lambda r: r.update(bounds=[[-0.03, -0.03], [0.03, 0.03]])),
    ],
    ids=["initial_knobs", "reading", "header-bounds"],
)
def test_an_edited_log_is_refused_on_resume_and_by_report(tmp_path, capsys, machines, kind, change):
    """Edit the first start's initial knobs, a reading, or the header's bounds: --resume exits
    2 naming the edited line, builds no machine and appends nothing; pigp report exits 2 too."""
    log, more = finished_run(tmp_path)
    capsys.readouterr()
    line = line_of(log, kind, 1 if kind == "evaluation" else 0)
    edit(log, line, change)
    before = log.read_bytes()
    n_machines = len(machines)
    assert cli.main(["optimize", "--resume", str(log), "--config", more]) == 2
    err = capsys.readouterr().err
    assert f"run.jsonl:{line}: the record does not match the log's hash chain" in err
    assert len(machines) == n_machines and log.read_bytes() == before
    assert cli.main(["report", str(log), "-o", str(tmp_path / "r")]) == 2
    assert f"run.jsonl:{line}: the record does not match" in capsys.readouterr().err
    assert not (tmp_path / "r.png").exists()


def test_a_deleted_middle_line_is_refused(tmp_path, capsys):
    """Remove an evaluation's intent from the middle: refused at the line after the gap."""
    log, more = finished_run(tmp_path)
    capsys.readouterr()
    lines = log.read_text().splitlines(keepends=True)
    gap = line_of(log, "intent", 2)
    log.write_text("".join(lines[: gap - 1] + lines[gap:]))
    assert cli.main(["optimize", "--resume", str(log), "--config", more]) == 2
    assert f"run.jsonl:{gap}: the record does not match" in capsys.readouterr().err


def test_a_torn_last_line_resumes_with_one_plain_warning(tmp_path):
    """A crash cut the last line: the resume drops it with ONE warning line (no Python source
    line), continues the chain and completes; the whole log verifies afterwards."""
    log, more = finished_run(tmp_path)
    lines = log.read_text().splitlines(keepends=True)
    log.write_text("".join(lines[:-1]) + lines[-1][:25])  # the end record cut mid-write
    proc = run_child(["optimize", "--resume", str(log), "--config", more, "--quiet"])
    assert proc.returncode == 0, proc.stderr
    warnings = [ln for ln in proc.stderr.splitlines() if "cut short" in ln]
    assert len(warnings) == 1 and warnings[0].startswith("warning: "), proc.stderr
    assert plain_stderr(proc.stderr) == [], proc.stderr
    records = read_log(log)
    assert records.n_evaluations == 9 and records.verified and records.torn_line is None


def downgrade(log: Path, *, as_written: bool, change=None) -> None:
    """The log as version 2: every hash removed; ``as_written``: also every field and run-file
    option version 2 never wrote (the log as that version would have written it); ``change``
    edits the first start record."""
    lines = []
    for line in log.read_text().splitlines():
        record = json.loads(line)
        record.pop("hash")
        if record["type"] == "header":
            record["version"] = 2
        if as_written and record["type"] != "notice":
            record = {k: v for k, v in record.items() if k in LEGACY_FIELDS[record["type"]]}
            if record["type"] == "header":
                config = record["config"]
                kind = f"machine:{config['machine']['kind']}"
                config["machine"] = {k: v for k, v in config["machine"].items()
                                     if k in LEGACY_CONFIG[kind]}  # fmt: skip
                record["config"] = {k: v for k, v in config.items() if k in LEGACY_CONFIG[""]}
                record["config_sha256"] = config_digest(record["config"])
        if change is not None and record["type"] == "start":
            change(record)
            change = None
        lines.append(json.dumps(record, separators=(",", ":")))
    log.write_text("\n".join(lines) + "\n")


def test_an_old_log_without_a_chain_resumes_with_a_warning(tmp_path, capsys):
    """A version-2 log (no hashes, only what version 2 wrote): it resumes, with one warning that
    it cannot be verified, and stays unchained."""
    log, more = finished_run(tmp_path)
    downgrade(log, as_written=True)
    capsys.readouterr()
    assert cli.main(["optimize", "--resume", str(log), "--config", more, "--quiet"]) == 0
    err = capsys.readouterr().err
    assert err.count("without a hash chain: its records cannot be verified") == 1
    records = read_log(log, warn=False)
    assert records.n_evaluations == 9 and not records.chained
    assert all("hash" not in r for r in records.evaluations)


def test_a_downgraded_log_is_refused(tmp_path, capsys):
    """A current log with its version set to 2 and every hash deleted (the chain switched off):
    its header stores options version 2 did not have, so --resume and pigp report refuse it
    (exit 2, naming line 1 and the options)."""
    log, more = finished_run(tmp_path)
    downgrade(log, as_written=False)
    capsys.readouterr()
    assert cli.main(["optimize", "--resume", str(log), "--config", more, "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "run.jsonl:1: the log claims run-log version 2 (no hash chain) but" in err
    assert "restore_timeout" in err and "refused" in err
    assert cli.main(["report", str(log)]) == 2
    assert "claims run-log version 2" in capsys.readouterr().err


def test_a_version_3_log_without_its_hashes_is_refused(tmp_path, capsys):
    """A version-3 log whose hashes were all deleted cannot be resumed or reported."""
    log, more = finished_run(tmp_path)
    text = "".join(
        json.dumps({k: v for k, v in json.loads(ln).items() if k != "hash"}) + "\n"
        for ln in log.read_text().splitlines()
    )
    log.write_text(text)
    assert cli.main(["optimize", "--resume", str(log), "--config", more, "--quiet"]) == 2
    assert "run.jsonl:1: the record has no 'hash'" in capsys.readouterr().err
    assert cli.main(["report", str(log)]) == 2


def test_an_old_log_whose_restore_target_is_far_needs_confirmation(tmp_path, capsys):
    """A version-2 log whose initial knobs are more than max_step from the setpoints now: the
    target is shown and the resume refused (exit 2, the log untouched); with
    --accept-restore-target it resumes and restores there."""
    log, more = finished_run(tmp_path)
    far = [0.009, -0.009]  # the knobs stand at the start, near 0: > max_step (0.2 * 0.01) away
    downgrade(log, as_written=True, change=lambda r: r.update(initial_knobs=far))
    before = log.read_text()
    capsys.readouterr()
    assert cli.main(["optimize", "--resume", str(log), "--config", more, "--quiet"]) == 2
    captured = capsys.readouterr()
    assert "the initial knobs of the first start (the restore target)" in captured.out
    assert "0.009" in captured.out and "--accept-restore-target" in captured.err
    assert "cannot be verified and is more than max_step" in captured.err
    assert log.read_text() == before
    args = ["optimize", "--resume", str(log), "--config", more, "--quiet"]
    assert cli.main([*args, "--accept-restore-target"]) == 0
    assert read_log(log, warn=False).last_end["final_knobs"] == far


# -------------------------------------------------------------------------- run files
@pytest.mark.parametrize(
    ("over", "message"),
    [
        ({"max_step": 1000}, r"max_step 1000 is above 1: more than a whole half-range"),
        ({"max_step": 2}, r"max_step 2 is above 1"),
        ({"max_step": {"01G-QSS4": 0.5, "02G-QSS3": 0.001}}, r"01G-QSS4 0.5 > 0.01 exceed half"),
        ({"max_step": True}, r"True is not a step limit"),
        ({"knobs": {k: [False, True] for k in KNOBS}}, r"knobs.01G-QSS4.0: .*got False"),
        ({"knobs": {k: ["-0.01", "0.01"] for k in KNOBS}}, r"got '-0.01' \(booleans and"),
        ({"budget": "5"}, r"budget: Input should be a valid integer, got '5'"),
        ({"budget": True}, r"budget: Input should be a valid integer, got True"),
        ({"objective": {"maximize": "yes"}}, r"objective.maximize: .*got 'yes'"),
        (
            {"method": {"name": "nelder-mead", "options": {"initial_simplex_size": "0.2"}}},
            r"initial_simplex_size: '0.2' is quoted text",
        ),
        (
            {"method": {"name": "nelder-mead", "options": {"initial_simplex_size": True}}},
            r"initial_simplex_size: True is not a number",
        ),
    ],
    ids=[
        "max_step-1000",
        "max_step-2",
        "max_step-per-knob",
        "max_step-true",
        "bounds-bool",
        "bounds-str",
        "budget-str",
        "budget-bool",
        "maximize-str",
        "option-str",
        "option-bool",
    ],
)
def test_run_files_that_must_be_refused_exit_2_before_any_machine(
    tmp_path, capsys, machines, over, message
):
    """Each is refused with exit 2 and one message; no machine is built, no log written."""
    import re

    assert cli.main(["optimize", "--config", write_config(tmp_path, **over)]) == 2
    err = capsys.readouterr().err
    assert re.search(message, err), err
    assert "Traceback" not in err and machines == [] and not (tmp_path / "run.jsonl").exists()


def test_max_step_unlimited_and_one_still_run(tmp_path, capsys):
    """max_step 1 (a half-range per set) and unlimited (said on purpose) are accepted."""
    assert cli.main(["optimize", "--config", write_config(tmp_path, max_step=1), "--quiet"]) == 0
    config = write_config(tmp_path, "u.yaml", max_step="unlimited", log="u.jsonl", budget=3)
    assert cli.main(["optimize", "--config", config, "--quiet"]) == 0
    assert "no step limit" in capsys.readouterr().err


def test_a_folder_or_unreadable_run_file_is_one_line(tmp_path, capsys, monkeypatch):
    """--config DIR, a file that cannot be read, a binary file: exit 2, one line each."""
    assert cli.main(["optimize", "--config", str(tmp_path)]) == 2
    assert capsys.readouterr().err.strip().endswith("is a folder, not a run file (give the YAML "
                                                    "or JSON file)")  # fmt: skip
    (tmp_path / "bin.yaml").write_bytes(b"\xff\xfe\x00knobs")
    assert cli.main(["optimize", "--config", str(tmp_path / "bin.yaml")]) == 2
    assert "not a text file (UTF-8)" in capsys.readouterr().err
    config = write_config(tmp_path)
    real = Path.read_text

    def read_text(self, *a, **k):
        if self.name == "run.yaml":
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), str(self))
        return real(self, *a, **k)

    monkeypatch.setattr(Path, "read_text", read_text)
    assert cli.main(["optimize", "--config", config]) == 2
    err = capsys.readouterr().err
    assert "cannot read the run file: Permission denied" in err and len(err.splitlines()) == 1


def test_a_log_held_by_a_running_run_exits_4(tmp_path, capsys):
    """Another process holds the log's lock (a run in progress): a run with the same log path
    is refused with exit 4 naming the holder, not 2 ("exists"); the log is untouched."""
    log, _ = finished_run(tmp_path, budget=3)
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys, time; from pigp_torch.data.runlock import log_lock; "
            "lock = log_lock(sys.argv[1]).acquire(); print('held', flush=True); time.sleep(60)",
            str(log),
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout.readline().strip() == "held"
        before = log.read_bytes()
        capsys.readouterr()
        assert cli.main(["optimize", "--config", write_config(tmp_path, budget=3)]) == 4
        err = capsys.readouterr().err
        assert f"run log {log} is in use by PID {holder.pid}" in err
        assert log.read_bytes() == before
    finally:
        holder.kill()
        holder.wait(timeout=10)


def test_a_dry_run_next_to_an_existing_log_says_what_a_run_would_do(tmp_path, capsys):
    """The dry run is not refused: it names the log, what it holds, and that a run would be
    refused and should --resume it; the log is unchanged."""
    log, _ = finished_run(tmp_path, budget=3)
    before = log.read_bytes()
    capsys.readouterr()
    config = write_config(tmp_path, budget=3)
    assert cli.main(["optimize", "--config", config, "--dry-run"]) == 0
    err = capsys.readouterr().err
    assert f"the run log {log} exists: continue it with --resume {log}" in err
    assert "it holds 3 evaluation(s), ended completed" in err
    assert "a run with this file would be refused (exit 2)" in err
    assert log.read_bytes() == before
    assert cli.main(["optimize", "--config", config]) == 2


def test_report_draws_a_torn_log_with_one_plain_warning(tmp_path, capsys):
    """`pigp report` on a log whose last line a crash cut: drawn, exit 0, the torn line named in
    one `warning:` line on stderr."""
    log, _ = finished_run(tmp_path, budget=3)
    text = log.read_text()
    log.write_text(text[: len(text) - 30])
    capsys.readouterr()
    assert cli.main(["report", str(log), "-o", str(tmp_path / "r")]) == 0
    err = capsys.readouterr().err
    assert [ln for ln in err.splitlines() if ln] == [
        f"warning: {log}: line {len(text.splitlines())} was cut short by an interrupted write "
        "(a crash); it is ignored"
    ]
    assert (tmp_path / "r.png").is_file()
