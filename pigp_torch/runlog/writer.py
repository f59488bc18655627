r"""Writing a run log: :class:`RunLog` (one fsynced JSON line per record, under the log's lock)
and the format's constants."""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from pigp_torch._utils import utc_now
from pigp_torch.runlog.format import END_STATUSES, FORMAT_TAG, FORMAT_VERSION, RECORD_TYPES, floats
from pigp_torch.runlog.reader import read_log


def _package_version() -> str:
    from pigp_torch._version import __version__

    return __version__


class RunLog:
    r"""Append-only JSON-lines writer; every record is flushed and fsynced before returning.

    Create a new log with :meth:`create` (writes the header) or continue one with
    :meth:`append` (a resume). Usable as a context manager.

    Attributes:
        path: the file.
        header: the header record.
    """

    def __init__(self, path: str | Path, header: dict, handle, lock=None) -> None:
        # use create() / append(); this only wires an open handle (and the lock it holds)
        self.path = Path(path)
        self.header = header
        self._f = handle
        self._lock = lock

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

        The header holds ``type``, ``format``, ``version``, ``package_version``, ``created`` and
        the entries of ``header`` (which must be JSON-serializable; it should include
        ``knob_names``).

        Args:
            path: the new log.
            header: entries of the header record.
            overwrite: replace an existing file.
            lock: ``True`` (default) takes the log's lock, held until :meth:`close`; an
                acquired :class:`~pigp_torch.runlock.RunLock` is adopted (released at close);
                ``False``: no lock.

        Raises:
            FileExistsError: ``path`` exists and ``overwrite`` is false (a log is never clobbered
                by accident: continue it with :meth:`append`).
            ValueError: ``header`` is not JSON-serializable or uses a reserved key.
            pigp_torch.runlock.LockHeld: another process holds the log's lock.
        """
        path = Path(path)
        extra = dict(header or {})
        reserved = sorted({"type", "format", "version"} & set(extra))
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
        line = _dumps(record)  # fail before creating the file
        if path.exists() and not overwrite:
            raise FileExistsError(f"run log {path} exists: continue it with RunLog.append")
        if path.parent != Path():
            path.parent.mkdir(parents=True, exist_ok=True)
        held = _take_lock(path, lock)
        try:
            handle = open(path, "w" if overwrite else "x", encoding="utf-8")
        except BaseException:
            if held is not None and held is not lock:
                held.release()
            raise
        log = cls(path, record, handle, held)
        log._write_line(line)
        _fsync_dir(path.parent)
        return log

    @classmethod
    def append(cls, path: str | Path, *, lock=True) -> RunLog:
        r"""Open an existing log to continue it (resume).

        The log's lock is taken first (``lock`` as in :meth:`create`); then a last line cut
        short by a crash during a write (no final newline) is removed.

        Raises:
            FileNotFoundError: no such file.
            ValueError: the file is not a run log.
            pigp_torch.runlock.LockHeld: another process holds the log's lock.
        """
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"no run log {path}")
        held = _take_lock(path, lock)
        try:
            records = read_log(path)  # validates the header
            with open(path, "rb+") as f:
                data = f.read()
                if data and not data.endswith(b"\n"):
                    f.truncate(data.rfind(b"\n") + 1)
                    f.flush()
                    os.fsync(f.fileno())
            handle = open(path, "a", encoding="utf-8")
        except BaseException:
            if held is not None and held is not lock:
                held.release()
            raise
        return cls(path, records.header, handle, held)

    # -- writing ---------------------------------------------------------------------------------
    def _write_line(self, line: str) -> None:
        if self._f is None or self._f.closed:
            raise ValueError(f"run log {self.path} is closed")
        self._f.write(line + "\n")
        self._f.flush()
        os.fsync(self._f.fileno())

    def write(self, record_type: str, **fields) -> dict:
        """Append one record ``{"type": record_type, **fields}``; returns it."""
        if record_type not in RECORD_TYPES[1:]:
            raise ValueError(f"record type must be one of {RECORD_TYPES[1:]}, got {record_type!r}")
        record = {"type": record_type, **fields}
        self._write_line(_dumps(record))
        return record

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
        return self.write(
            "intent",
            time=utc_now(),
            x=floats(x),
            purpose=str(purpose),
            step=None if step is None else int(step),
            **fields,
        )

    def log_evaluation(self, step: int, x, y: float, **fields) -> dict:
        """Record one evaluation: ``step``, ``x`` (knob order of the header), ``y`` and extras."""
        return self.write("evaluation", step=int(step), x=floats(x), y=float(y), **fields)

    def log_end(self, status: str, reason: str = "", **fields) -> dict:
        """Record how a session ended (``status`` one of :data:`END_STATUSES`)."""
        if status not in END_STATUSES:
            raise ValueError(f"status must be one of {END_STATUSES}, got {status!r}")
        return self.write("end", time=utc_now(), status=status, reason=str(reason), **fields)

    def close(self) -> None:
        """Close the file and release the log's lock (idempotent)."""
        try:
            if self._f is not None and not self._f.closed:
                self._f.close()
        finally:
            if self._lock is not None:
                self._lock.release()
                self._lock = None

    def __enter__(self) -> RunLog:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"RunLog({str(self.path)!r})"


def _take_lock(path: Path, lock):
    """The log's lock per ``lock`` (True: take it; a RunLock: adopt it; False/None: none)."""
    if lock is True:
        from pigp_torch.runlock import log_lock

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
