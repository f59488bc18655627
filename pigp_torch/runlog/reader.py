r"""Reading a run log: :func:`read_log` -> :class:`RunRecords` (records by type, checked)."""

from __future__ import annotations

import json
import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import torch

from pigp_torch._utils import DTYPE
from pigp_torch.runlog.format import (
    FORMAT_TAG,
    READABLE_VERSIONS,
    RECORD_TYPES,
)


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
