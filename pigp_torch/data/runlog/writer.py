r"""Writing a run log: :class:`RunLog` (one fsynced, hash-chained JSON line per record, under the
log's lock)."""

from __future__ import annotations

import contextlib
import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from pigp_torch._utils import utc_now
from pigp_torch.data.runlog.format import (
    APPENDED_KEY,
    END_STATUSES,
    FORMAT_TAG,
    FORMAT_VERSION,
    HASH_KEY,
    RECORD_TYPES,
    LogWriteError,
    chain_hash,
    floats,
)
from pigp_torch.data.runlog.reader import read_log


def _package_version() -> str:
    from pigp_torch._version import __version__

    return __version__


class RunLog:
    r"""Append-only JSON-lines writer; every record is written, then fsynced, before returning.

    Create a new log with :meth:`create` (writes the header) or continue one with
    :meth:`append` (a resume). Usable as a context manager.

    Each record gets its ``hash`` (the chain of :mod:`pigp_torch.data.runlog.format`) and goes to
    the file in one unbuffered ``os.write`` followed by ``os.fsync``. A write that fails (disk full,
    I/O error) raises :class:`~pigp_torch.data.runlog.format.LogWriteError` and leaves nothing of
    the record in the file: the file is cut back to its last complete record (if even that fails,
    every later write is refused, so a partial line never ends up inside the log). A later record
    may still be written once space is free again; the chain continues from the last record
    written.

    Attributes:
        path: the file.
        header: the header record.
        write_error: the first failed write's message (``None`` while every write succeeded).
        end_record: the last record given to :meth:`log_end`, written or not (``None`` before).
        end_written: whether that end record reached the file.
        intents_written: ``intent`` records written through this object (settings commanded in
            this session).
    """

    def __init__(
        self, path: str | Path, header: dict, fd: int, lock=None, *, chain=None, size: int = 0
    ) -> None:
        # use create() / append(); this only wires an open file descriptor (and the lock it holds)
        self.path = Path(path)
        self.header = header
        self._fd = fd
        self._lock = lock
        self._chain = chain  # the last record's hash; None: an unchained (older) log
        self._size = int(size)  # bytes of complete records
        self._broken = False  # a failed write could not be undone: refuse every later write
        self.write_error: str | None = None
        self.end_record: dict | None = None
        self.end_written = False
        self.intents_written = 0

    # -- opening ---------------------------------------------------------------------------------
    @classmethod
    def create(
        cls,
        path: str | Path,
        header: Mapping[str, Any] | None = None,
        *,
        overwrite: bool = False,
        lock=True,
    ) -> RunLog:
        r"""Start a new log at ``path`` with a header record.

        The header holds ``type``, ``format``, ``version``, ``package_version``, ``created``, the
        entries of ``header`` (which must be JSON-serializable; it should include
        ``knob_names``) and its ``hash``. If the header cannot be written (disk full) the new
        file is removed and the lock released, so no empty log is left behind.

        Args:
            path: the new log.
            header: entries of the header record.
            overwrite: replace an existing file.
            lock: ``True`` (default) takes the log's lock, held until :meth:`close`; an
                acquired :class:`~pigp_torch.data.runlock.RunLock` is adopted (released at close);
                ``False``: no lock.

        Raises:
            FileExistsError: ``path`` exists and ``overwrite`` is false (a log is never clobbered
                by accident: continue it with :meth:`append`).
            ValueError: ``header`` is not JSON-serializable or uses a reserved key.
            LogWriteError: the header could not be written (the file was removed).
            pigp_torch.data.runlock.LockHeld: another process holds the log's lock.
        """
        path = Path(path)
        extra = dict(header or {})
        reserved = sorted({"type", "format", "version", HASH_KEY} & set(extra))
        if reserved:
            raise ValueError(f"header keys {reserved} are reserved")
        record = {
            "type": "header",
            "format": FORMAT_TAG,
            "version": FORMAT_VERSION,
            "package_version": _package_version(),
            "created": utc_now(),
            **extra,
        }
        _dumps(record)  # fail before creating the file
        if path.exists() and not overwrite:
            raise FileExistsError(f"run log {path} exists: continue it with RunLog.append")
        if path.parent != Path():
            path.parent.mkdir(parents=True, exist_ok=True)
        held = _take_lock(path, lock)
        flags = os.O_WRONLY | os.O_CREAT | os.O_APPEND | getattr(os, "O_CLOEXEC", 0)
        flags |= os.O_TRUNC if overwrite else os.O_EXCL
        try:
            fd = os.open(path, flags, 0o644)
        except BaseException:
            if held is not None and held is not lock:
                held.release()
            raise
        log = cls(path, record, fd, held, chain="")
        try:
            log.header = log._append_record(record)
            _fsync_dir(path.parent)
        except BaseException:
            log._close_fd()
            with contextlib.suppress(OSError):
                path.unlink()  # no log without its header (the next run would say it exists)
            if held is not None and held is not lock:
                held.release()
            log._lock = None
            raise
        return log

    @classmethod
    def append(cls, path: str | Path, *, lock=True, warn: bool = True) -> RunLog:
        r"""Open an existing log to continue it (resume).

        The log's lock is taken first (``lock`` as in :meth:`create`); the log is read and its
        hash chain verified (:func:`~pigp_torch.data.runlog.read_log`, ``warn`` as there); then a
        last line cut short by a crash during a write (no final newline) is removed. New records
        continue the chain (a log without one, from an older version, stays without one; each
        record appended to it carries ``appended_by_version``, the version that wrote it).

        Raises:
            FileNotFoundError: no such file.
            ValueError: the file is not a run log, or its hash chain is broken.
            pigp_torch.data.runlock.LockHeld: another process holds the log's lock.
        """
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"no run log {path}")
        held = _take_lock(path, lock)
        try:
            records = read_log(path, warn=warn)  # validates the header and the chain
            with open(path, "rb+") as f:
                data = f.read()
                size = len(data)
                if data and not data.endswith(b"\n"):
                    size = data.rfind(b"\n") + 1
                    f.truncate(size)
                    f.flush()
                    os.fsync(f.fileno())
            fd = os.open(path, os.O_WRONLY | os.O_APPEND | getattr(os, "O_CLOEXEC", 0))
        except BaseException:
            if held is not None and held is not lock:
                held.release()
            raise
        chain = records.last_hash if records.chained else None
        return cls(path, records.header, fd, held, chain=chain, size=size)

    # -- writing ---------------------------------------------------------------------------------
    def _append_record(self, record: dict) -> dict:
        """Add the chain's hash to ``record``, write it as one line; returns the record written."""
        if self._fd is None:
            raise ValueError(f"run log {self.path} is closed")
        if self._chain is None:  # appended to an older version's log: say by whom
            record = {**record, APPENDED_KEY: FORMAT_VERSION}
        line = _dumps(record)
        digest = None
        if self._chain is not None:  # hash the record as a reader will see it (parsed back)
            digest = chain_hash(self._chain, json.loads(line))
            record = {**record, HASH_KEY: digest}
            line = _dumps(record)
        self._write_line(line, digest)
        return record

    def _write_line(self, line: str, digest: str | None = None) -> None:
        """Write ``line`` and a newline, fsync; then the chain moves on to ``digest``.

        Whatever interrupts the write (a failed ``os.write``, a signal's exception between two
        calls), the file ends up holding either the whole line — and the chain moves on — or
        none of it (cut back), so the chain always matches the file.
        """
        if self._fd is None:
            raise ValueError(f"run log {self.path} is closed")
        if self._broken:
            raise LogWriteError(
                f"could not write to the run log {self.path}: an earlier write failed and left "
                f"a partial record ({self.write_error})"
            )
        data = (line + "\n").encode("utf-8")
        done = False
        try:
            view = memoryview(data)
            while view:  # os.write may write part of the bytes
                view = view[os.write(self._fd, view) :]
            done = True
            os.fsync(self._fd)
        except OSError as err:
            reason = err.strerror or str(err)
            if self.write_error is None:
                self.write_error = reason
            self._cut_back()  # nothing of this record stays (not durable: fsync failed)
            raise LogWriteError(f"could not write to the run log {self.path}: {reason}") from err
        except BaseException:  # a signal's exception: keep the file and the chain in step
            try:
                done = done or os.fstat(self._fd).st_size == self._size + len(data)
            except OSError:
                done = False
            if not done:
                self._cut_back()
            else:
                self._commit(len(data), digest)
            raise
        self._commit(len(data), digest)

    def _commit(self, n_bytes: int, digest: str | None) -> None:
        self._size += n_bytes
        if self._chain is not None and digest is not None:
            self._chain = digest

    def _cut_back(self) -> None:
        """Cut the file back to its last complete record (refuse later writes if that fails)."""
        try:
            os.ftruncate(self._fd, self._size)
        except OSError:
            self._broken = True

    def write(self, record_type: str, **fields) -> dict:
        """Append one record ``{"type": record_type, **fields}`` (and its ``hash``); returns it.

        Raises:
            ValueError: an unknown record type, a reserved field, values that are not JSON
                (non-finite floats), or a closed log.
            LogWriteError: the record could not be written (nothing of it stays in the file).
        """
        if record_type not in RECORD_TYPES[1:]:
            raise ValueError(f"record type must be one of {RECORD_TYPES[1:]}, got {record_type!r}")
        if HASH_KEY in fields:
            raise ValueError(f"{HASH_KEY!r} is reserved for the hash chain")
        return self._append_record({"type": record_type, **fields})

    def log_start(self, initial_knobs, *, budget: int, first_step: int, **fields) -> dict:
        """Record the start of a session: where the knobs were, the budget, the first step."""
        return self.write(
            "start",
            time=utc_now(),
            initial_knobs=None if initial_knobs is None else floats(initial_knobs),
            budget=int(budget),
            first_step=int(first_step),
            **fields,
        )

    def log_intent(self, x, *, purpose: str, step: int | None, **fields) -> dict:
        """Record the setting about to be written (before the write), its purpose and step."""
        record = self.write(
            "intent",
            time=utc_now(),
            x=floats(x),
            purpose=str(purpose),
            step=None if step is None else int(step),
            **fields,
        )
        self.intents_written += 1
        return record

    def log_evaluation(self, step: int, x, y: float, **fields) -> dict:
        """Record one evaluation: ``step``, ``x`` (knob order of the header), ``y`` and extras."""
        return self.write("evaluation", step=int(step), x=floats(x), y=float(y), **fields)

    def log_end(self, status: str, reason: str = "", **fields) -> dict:
        """Record how a session ended (``status`` one of :data:`END_STATUSES`). The record is kept
        in :attr:`end_record` even when it cannot be written (:attr:`end_written` false), so
        the caller still knows how the session ended."""
        if status not in END_STATUSES:
            raise ValueError(f"status must be one of {END_STATUSES}, got {status!r}")
        self.end_record = {"type": "end", "time": utc_now(), "status": status}
        self.end_record.update(reason=str(reason), **fields)
        self.end_written = False
        fields = {k: v for k, v in self.end_record.items() if k != "type"}
        record = self.write("end", **fields)
        self.end_written = True
        return record

    def _close_fd(self) -> None:
        fd, self._fd = self._fd, None
        if fd is not None:
            with contextlib.suppress(OSError):  # every record was fsynced already
                os.close(fd)

    def close(self) -> None:
        """Close the file and release the log's lock (idempotent; never raises for the file)."""
        try:
            self._close_fd()
        finally:
            if self._lock is not None:
                self._lock.release()
                self._lock = None

    @property
    def closed(self) -> bool:
        return self._fd is None

    @property
    def moved(self) -> bool:
        """Whether a setting was commanded in this session (an ``intent`` written)."""
        return self.intents_written > 0

    def __enter__(self) -> RunLog:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"RunLog({str(self.path)!r})"


def _take_lock(path: Path, lock):
    """The log's lock per ``lock`` (True: take it; a RunLock: adopt it; False/None: none)."""
    if lock is True:
        from pigp_torch.data.runlock import log_lock

        return log_lock(path).acquire()
    if lock is False or lock is None:
        return None
    if not getattr(lock, "held", False):
        lock.acquire()
    return lock


def _dumps(record: Mapping[str, Any]) -> str:
    try:
        return json.dumps(record, allow_nan=False, separators=(",", ":"))
    except (TypeError, ValueError) as err:
        raise ValueError(f"run log record is not JSON-serializable (finite values): {err}") from err


def _fsync_dir(directory: Path) -> None:
    """Make a new file's directory entry durable too (POSIX; a no-op where unsupported)."""
    try:
        fd = os.open(directory if str(directory) else ".", os.O_RDONLY)
    except OSError:  # pragma: no cover - e.g. Windows
        return
    try:
        os.fsync(fd)
    except OSError:  # pragma: no cover
        pass
    finally:
        os.close(fd)
