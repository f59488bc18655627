r"""Reading a run log: :func:`read_log` -> :class:`RunRecords` (records by type, checked)."""

from __future__ import annotations

import json
import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import torch

from pigp_torch._utils import DTYPE
from pigp_torch.data.runlog.format import (
    CHAINED_VERSION,
    FORMAT_TAG,
    HASH_KEY,
    READABLE_VERSIONS,
    RECORD_TYPES,
    TornLineWarning,
    UnchainedLogWarning,
    chain_hash,
)
from pigp_torch.data.runlog.legacy import check_legacy


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
        chained: whether the log carries the hash chain (version 3); an older log cannot be
            verified.
        verified: whether the chain was checked (``read_log(verify=True)`` on a chained log).
        last_hash: the last complete record's ``hash`` (``None`` without a chain).
        torn_line: the number of a last line cut short by an interrupted write and ignored
            (``None`` if there was none).
        warnings: what a reader should be told (the torn line, a log without a chain), one line
            each, already phrased for a person.
    """

    path: Path
    header: dict
    starts: list[dict] = field(default_factory=list)
    evaluations: list[dict] = field(default_factory=list)
    ends: list[dict] = field(default_factory=list)
    intents: list[dict] = field(default_factory=list)
    discarded: list[dict] = field(default_factory=list)
    notices: list[dict] = field(default_factory=list)
    chained: bool = False
    verified: bool = False
    last_hash: str | None = None
    torn_line: int | None = None
    warnings: list[str] = field(default_factory=list)

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

    @property
    def observable_names(self) -> list[str]:
        """Names of the observables each reading also measured (the header's; ``[]``: none)."""
        return list(self.header.get("observable_names") or [])

    @property
    def observable_units(self) -> list[str]:
        """Units of :attr:`observable_names` (``[]`` when the header names none)."""
        return list(self.header.get("observable_units") or [])

    def observables(self) -> torch.Tensor | None:
        """``n x m`` observables of the readings (header order), ``None`` unless every
        evaluation has them (a log of a machine without observables, or an older log)."""
        if not self.evaluations or any("observables" not in r for r in self.evaluations):
            return None
        return torch.tensor([r["observables"] for r in self.evaluations], dtype=DTYPE)

    def best(self, maximize: bool = True) -> tuple[int, torch.Tensor, float] | None:
        """``(step, x, y)`` of the best reading (first on ties), ``None`` without evaluations."""
        if not self.evaluations:
            return None
        Y = self.Y()
        i = int(Y.argmax() if maximize else Y.argmin())
        return i, self.X()[i], float(Y[i])


def read_log(path: str | Path, *, verify: bool = True, warn: bool = True) -> RunRecords:
    r"""Read and check a run log.

    Checks: the first record is a header with the expected format tag and version; every record has
    a known type; evaluation steps are ``0, 1, 2, ...`` with ``x`` of ``len(knob_names)`` finite
    values and a finite ``y`` (and ``observables``, where logged, finite values, one per name of the
    header's ``observable_names``); with ``verify`` (default) every record of a version-3 log
    matches the hash chain (:mod:`pigp_torch.data.runlog.format`), so a log edited anywhere is
    refused with the first line that does not match. A last line without its final newline was cut
    short by an interrupted write (the writer ends every record with one): it is skipped; an invalid
    line elsewhere is an error. A log of an older version (no chain) is read only where that
    version could have written every record (:func:`~pigp_torch.data.runlog.legacy.check_legacy`:
    no hash, no newer record type, field or run-file option), but cannot be verified.

    Each returned record carries ``_line`` (its 1-based line number).

    Args:
        path: the run log.
        verify: check the hash chain (``False``: read an edited log anyway, e.g. to inspect it).
        warn: issue a :class:`~pigp_torch.data.runlog.format.TornLineWarning` for a cut last line
            and an :class:`~pigp_torch.data.runlog.format.UnchainedLogWarning` for a log without a
            chain (the same lines are in :attr:`RunRecords.warnings` either way).

    Raises:
        FileNotFoundError: no such file.
        ValueError: not a run log, an inconsistent one, or (``verify``) one whose hash chain is
            broken (the message names the line).
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as err:
        raise ValueError(f"{path} is not a run log (not UTF-8 text: {err.reason})") from None
    except IsADirectoryError:
        raise ValueError(f"{path} is a folder, not a run log") from None
    lines = text.split("\n")
    complete = text.endswith("\n")
    if lines and lines[-1] == "":
        lines.pop()
    notes: list[str] = []
    torn = None
    if lines and not complete:
        torn = len(lines)
        lines.pop()
        notes.append(
            f"{path}: line {torn} was cut short by an interrupted write (a crash); it is ignored"
        )
    records: list[dict] = []
    for k, line in enumerate(lines, start=1):
        try:
            rec = json.loads(line)
        except json.JSONDecodeError as err:
            raise ValueError(f"{path}:{k}: not a JSON record ({err})") from err
        if not isinstance(rec, dict) or rec.get("type") not in RECORD_TYPES:
            raise ValueError(f"{path}:{k}: not a run-log record (type one of {RECORD_TYPES})")
        records.append(rec)
    if not records or records[0]["type"] != "header":
        raise ValueError(f"{path} is not a run log: the first record is not a header")
    header = records[0]
    if header.get("format") != FORMAT_TAG:
        raise ValueError(f"{path} is not a run log (format tag {header.get('format')!r})")
    version = header.get("version")
    if version not in READABLE_VERSIONS or isinstance(version, bool):
        raise ValueError(f"{path}: unsupported run-log version {version!r}")
    chained = version >= CHAINED_VERSION
    if not chained and HASH_KEY in header:
        raise ValueError(
            f"{path}:1: the header carries a hash but claims version {version} (the log was edited)"
        )
    if not chained:  # a downgraded log: what that version never wrote gives it away
        check_legacy(records, version, path)
    last_hash = _check_chain(records, path, verify) if chained else None
    if not chained:
        notes.append(
            f"{path}: written by an older version (run-log version {version}) without a hash "
            "chain: its records cannot be verified"
        )
    for k, rec in enumerate(records, start=1):
        rec["_line"] = k
    out = RunRecords(path=path, header=header, chained=chained, verified=chained and verify)
    out.last_hash, out.torn_line, out.warnings = last_hash, torn, notes
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
            _check_observables(rec, len(out.observable_names) or None, path)
            d = d or len(rec["x"])
            out.evaluations.append(rec)
    if warn:
        if torn is not None:
            warnings.warn(notes[0], TornLineWarning, stacklevel=2)
        if not chained:
            warnings.warn(notes[-1], UnchainedLogWarning, stacklevel=2)
    return out


def _check_chain(records: list[dict], path: Path, verify: bool) -> str | None:
    """Verify the hash chain of ``records`` (``verify``) and return the last hash.

    Raises:
        ValueError: a record without its hash, or the first record that does not match.
    """
    previous = ""
    for k, rec in enumerate(records, start=1):
        logged = rec.get(HASH_KEY)
        if not verify:
            previous = logged if isinstance(logged, str) else previous
            continue
        if not isinstance(logged, str):
            raise ValueError(
                f"{path}:{k}: the record has no {HASH_KEY!r} (the log was edited); refused"
            )
        if chain_hash(previous, rec) != logged:
            raise ValueError(
                f"{path}:{k}: the record does not match the log's hash chain: the log was "
                f"edited at line {k} (a record changed, or one removed or added before it); "
                "refused"
            )
        previous = logged
    return previous


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


def _check_observables(rec: dict, m: int | None, path: Path) -> None:
    obs = rec.get("observables")
    if obs is None:
        return
    where = f"{path}:{rec['_line']}"
    if not isinstance(obs, list) or (m is not None and len(obs) != m):
        raise ValueError(f"{where}: observables must be a list of {m} values")
    if not all(
        isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in obs
    ):
        raise ValueError(f"{where}: observables must be finite numbers")
