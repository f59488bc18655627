r"""The run log: every evaluation of an online run, on disk before the next step, and its replay.

A run log is a JSON-lines file (one JSON object per line), append-only. Record types:

* ``header`` (first line, once): ``format``/``version`` tags, ``package_version``,
  ``created`` (UTC, ISO 8601), ``knob_names`` and whatever the writer adds — the command
  ``pigp optimize`` stores the validated configuration and the prior's provenance (file path,
  sha256 of its bytes, its ``provenance`` metadata).
* ``start`` (one per session: the first run and each resume): ``time``, ``initial_knobs`` (the
  knobs found on the machine, where they are put back), ``budget``, ``first_step``.
* ``intent`` (one before every ``set`` the loop sends, fsynced before the write): ``x`` (the
  setting about to be written), ``purpose`` (``"evaluation"`` or ``"restore initial"`` /
  ``"restore best"``), ``step`` (the evaluation it serves, ``null`` for a restore), ``part`` /
  ``parts`` (its place in a ramp). After a crash the last one is the last commanded setting.
* ``discarded`` (a reading thrown away because the machine's state changed during it): ``step``,
  ``y``, ``reason``, ``time``.
* ``evaluation`` (one per measurement): ``step`` (0, 1, ...), ``x`` (knob values in
  ``knob_names`` order), ``y``, ``reads`` (read attempts it took), ``t_set`` / ``t_read`` (UNIX
  times before the move and after the reading), ``ask_time_s`` and ``eval_time_s``, and
  ``reading`` (what the machine reports about the reading, e.g. the objective PV's timestamps).
* ``end`` (one per session that ended in Python): ``status`` (``"completed"``,
  ``"interrupted"``, ``"aborted"`` or ``"failed"``), ``reason``, ``restored_to``,
  ``final_knobs`` (the readback after the restore), ``best``, ``n_evaluations`` and, on a machine,
  ``restored`` (whether the knobs were put back), ``last_setpoint`` (the last setting written)
  and ``restore_attempts``.

While a :class:`RunLog` is open it holds the log's lock (:func:`pigp_torch.runlock.log_lock`,
``<log>.lock``): a second writer is refused with :class:`~pigp_torch.runlock.LockHeld`.

Each record is written with one ``write``, then ``flush`` and ``os.fsync``: a crash (even a
power cut after the call returned) loses no completed evaluation. A last line cut short by a crash
during a write is ignored when reading (with a warning) and cut off before appending.

Why JSON lines and not CSV/Parquet: records of different types share one file, a reader needs
nothing but ``json``, appending never rewrites earlier bytes, and floats round-trip exactly
(``json`` writes ``repr(float)``).

:func:`replay` rebuilds an optimizer from the logged evaluations by re-running its asks; every
optimizer of the package is deterministic given its seed and the data told, so the rebuilt state is
the state the run had.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import warnings
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from pigp_torch._utils import DTYPE, utc_now

#: Tag of the header record, checked on read.
FORMAT_TAG = "pigp_torch.RunLog"
FORMAT_VERSION = 2
#: Versions :func:`read_log` accepts (version 1 had no intent or discarded records).
READABLE_VERSIONS = (1, 2)
RECORD_TYPES = ("header", "start", "evaluation", "end", "intent", "discarded", "notice")
END_STATUSES = ("completed", "interrupted", "aborted", "failed")


class ReplayError(ValueError):
    """Replaying a run log did not reproduce the logged run (other config, prior or seed)."""


def file_sha256(path: str | Path) -> str:
    """Hex sha256 of a file's bytes (read in 1 MiB chunks)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _package_version() -> str:
    from pigp_torch._version import __version__

    return __version__


def _floats(x) -> list[float]:
    if isinstance(x, torch.Tensor):
        return [float(v) for v in x.detach().reshape(-1).tolist()]
    return [float(v) for v in x]


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
            initial_knobs=None if initial_knobs is None else _floats(initial_knobs),
            budget=int(budget),
            first_step=int(first_step),
            **fields,
        )

    def log_intent(self, x, *, purpose: str, step: int | None, **fields) -> dict:
        """Record the setting about to be written (before the write), its purpose and step."""
        return self.write(
            "intent",
            time=utc_now(),
            x=_floats(x),
            purpose=str(purpose),
            step=None if step is None else int(step),
            **fields,
        )

    def log_evaluation(self, step: int, x, y: float, **fields) -> dict:
        """Record one evaluation: ``step``, ``x`` (knob order of the header), ``y`` and extras."""
        return self.write("evaluation", step=int(step), x=_floats(x), y=float(y), **fields)

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


# ------------------------------------------------------------------------------------- reading
@dataclass
class RunRecords:
    r"""The records of a run log, by type, in file order.

    Attributes:
        path: the file read.
        header: the header record.
        starts: ``start`` records (one per session).
        evaluations: ``evaluation`` records, steps ``0 .. n-1`` in order.
        ends: ``end`` records.
        intents: ``intent`` records (the settings commanded, in order).
        discarded: ``discarded`` records (readings thrown away).
        notices: ``notice`` records (what the optimizer decided about itself, e.g. that its
            physics prior does not explain the readings).
    """

    path: Path
    header: dict
    starts: list[dict] = field(default_factory=list)
    evaluations: list[dict] = field(default_factory=list)
    ends: list[dict] = field(default_factory=list)
    intents: list[dict] = field(default_factory=list)
    discarded: list[dict] = field(default_factory=list)
    notices: list[dict] = field(default_factory=list)

    @property
    def last_intent(self) -> dict | None:
        """The last commanded setting (an ``intent`` record), ``None`` if none was logged."""
        return self.intents[-1] if self.intents else None

    @property
    def initial_knobs(self) -> list[float] | None:
        """The initial knobs of the run's first start (where a restore puts the knobs)."""
        for start in self.starts:
            if start.get("initial_knobs") is not None:
                return list(start["initial_knobs"])
        return None

    @property
    def knob_names(self) -> list[str]:
        return list(self.header.get("knob_names") or [])

    @property
    def n_evaluations(self) -> int:
        return len(self.evaluations)

    @property
    def last_end(self) -> dict | None:
        """The end record of the last session, ``None`` if it has none (a hard crash)."""
        if not self.ends or (self.starts and self.ends[-1]["_line"] < self.starts[-1]["_line"]):
            return None
        return self.ends[-1]

    def X(self) -> torch.Tensor:
        """``n x d`` evaluated knob settings."""
        if not self.evaluations:
            return torch.zeros(0, len(self.knob_names), dtype=DTYPE)
        return torch.tensor([r["x"] for r in self.evaluations], dtype=DTYPE)

    def Y(self) -> torch.Tensor:
        """``n`` readings."""
        return torch.tensor([r["y"] for r in self.evaluations], dtype=DTYPE)

    def best(self, maximize: bool = True) -> tuple[int, torch.Tensor, float] | None:
        """``(step, x, y)`` of the best reading (first on ties), ``None`` without evaluations."""
        if not self.evaluations:
            return None
        Y = self.Y()
        i = int(Y.argmax() if maximize else Y.argmin())
        return i, self.X()[i], float(Y[i])


def read_log(path: str | Path) -> RunRecords:
    r"""Read and check a run log.

    Checks: the first record is a header with the expected format tag and version; every record
    has a known type; evaluation steps are ``0, 1, 2, ...`` with ``x`` of ``len(knob_names)``
    finite values and a finite ``y``. A last line cut short (no final newline, not valid JSON) is
    skipped with a warning; an invalid line elsewhere is an error.

    Each returned record carries ``_line`` (its 1-based line number).

    Raises:
        FileNotFoundError: no such file.
        ValueError: not a run log, or an inconsistent one (the message names the line).
    """
    path = Path(path)
    text = path.read_text(encoding="utf-8")
    lines = text.split("\n")
    complete = text.endswith("\n")
    if lines and lines[-1] == "":
        lines.pop()
    records: list[dict] = []
    for k, line in enumerate(lines, start=1):
        try:
            rec = json.loads(line)
        except json.JSONDecodeError as err:
            if k == len(lines) and not complete:
                warnings.warn(
                    f"{path}: ignoring the last line, cut short by an interrupted write",
                    stacklevel=2,
                )
                break
            raise ValueError(f"{path}:{k}: not a JSON record ({err})") from err
        if not isinstance(rec, dict) or rec.get("type") not in RECORD_TYPES:
            raise ValueError(f"{path}:{k}: not a run-log record (type one of {RECORD_TYPES})")
        rec["_line"] = k
        records.append(rec)
    if not records or records[0]["type"] != "header":
        raise ValueError(f"{path} is not a run log: the first record is not a header")
    header = records[0]
    if header.get("format") != FORMAT_TAG:
        raise ValueError(f"{path} is not a run log (format tag {header.get('format')!r})")
    if header.get("version") not in READABLE_VERSIONS:
        raise ValueError(f"{path}: unsupported run-log version {header.get('version')!r}")
    out = RunRecords(path=path, header=header)
    d = len(out.knob_names) or None
    for rec in records[1:]:
        kind = rec["type"]
        if kind == "header":
            raise ValueError(f"{path}:{rec['_line']}: a second header")
        if kind == "start":
            out.starts.append(rec)
        elif kind == "end":
            out.ends.append(rec)
        elif kind == "intent":
            out.intents.append(rec)
        elif kind == "discarded":
            out.discarded.append(rec)
        elif kind == "notice":
            out.notices.append(rec)
        else:
            _check_evaluation(rec, len(out.evaluations), d, path)
            d = d or len(rec["x"])
            out.evaluations.append(rec)
    return out


def _check_evaluation(rec: dict, expected_step: int, d: int | None, path: Path) -> None:
    where = f"{path}:{rec['_line']}"
    if rec.get("step") != expected_step:
        raise ValueError(f"{where}: evaluation step {rec.get('step')!r}, expected {expected_step}")
    x, y = rec.get("x"), rec.get("y")
    if not isinstance(x, list) or (d is not None and len(x) != d):
        raise ValueError(f"{where}: x must be a list of {d} knob values")
    values = [*x, y]
    if not all(isinstance(v, (int, float)) and math.isfinite(v) for v in values):
        raise ValueError(f"{where}: x and y must be finite numbers")


# ------------------------------------------------------------------------------------- replay
def _evaluations(records) -> list[dict]:
    if isinstance(records, RunRecords):
        return list(records.evaluations)
    records = list(records)
    for k, r in enumerate(records):
        if r.get("step", k) != k:
            raise ValueError(f"evaluation records must have steps 0, 1, ...; got {r.get('step')}")
    return records


def replay(
    optimizer,
    records: RunRecords | Iterable[Mapping[str, Any]],
    *,
    tol: float = 1e-6,
    progress: bool = False,
) -> int:
    r"""Rebuild an optimizer's state from logged evaluations; returns how many were told.

    ``optimizer`` must be fresh (nothing told), built exactly as in the logged run (same class,
    bounds, options, seed, prior). Step 0 is told as the start point; for every later record the
    optimizer is asked for its next point, which must equal the logged ``x`` within ``tol`` times
    each knob's range, and then told the logged ``(x, y)``. Asking is what makes the rebuilt state
    exact: direct-search coroutines advance their generators, model factories with internal state
    (e.g. warm-started hyperparameters) see the same sequence of calls, and the check proves the
    log and the optimizer agree. The cost is one ``ask`` per record (a GP fit and an acquisition
    optimization for BayesOpt).

    Args:
        optimizer: a fresh ask/tell optimizer.
        records: a :class:`RunRecords` or evaluation records (dicts with ``x`` and ``y``, in step
            order).
        tol: allowed difference between asked and logged points, a fraction of the knob range.
        progress: tqdm bar over the records.

    Raises:
        ReplayError: the optimizer already holds data, or an asked point differs from the logged
            one (the message names the step and both points).
    """
    evaluations = _evaluations(records)
    if getattr(optimizer, "n_told", 0):
        raise ReplayError("replay needs a fresh optimizer (this one has already been told data)")
    bounds = getattr(optimizer, "bounds", None)
    width = None if bounds is None else (bounds[1] - bounds[0])
    it = evaluations
    if progress:
        from tqdm.auto import tqdm

        it = tqdm(evaluations, desc="replaying the run log")
    for k, rec in enumerate(it):
        x = torch.tensor(_floats(rec["x"]), dtype=DTYPE)
        if k > 0:
            asked = torch.as_tensor(optimizer.ask(), dtype=DTYPE).reshape(-1)
            limit = tol * (width if width is not None else torch.ones_like(x))
            if asked.shape != x.shape or not bool(((asked - x).abs() <= limit).all()):
                raise ReplayError(
                    f"replay diverged at step {k}: the optimizer asks {asked.tolist()} but the "
                    f"log holds {x.tolist()}; the method, its options, seed or prior differ from "
                    "the logged run"
                )
        try:
            optimizer.tell(x, float(rec["y"]))
        except ValueError as err:
            raise ReplayError(f"replay failed at step {k}: {err}") from err
    return len(evaluations)


def evaluation_rows(
    records: RunRecords | Sequence[Mapping[str, Any]], knob_names: Sequence[str], method: str
) -> list[dict]:
    """Logged evaluations as rows of the :func:`pigp_torch.optimize` table."""
    rows = []
    for rec in _evaluations(records):
        row = {"step": int(rec["step"]), **dict(zip(knob_names, _floats(rec["x"]), strict=True))}
        row.update(
            y=float(rec["y"]),
            method=method,
            ask_time_s=float(rec.get("ask_time_s", 0.0)),
            eval_time_s=float(rec.get("eval_time_s", 0.0)),
        )
        rows.append(row)
    return rows
