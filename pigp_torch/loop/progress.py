r"""One progress line per evaluation: step N of M, reading, best so far, largest knob move, time.

:class:`ProgressLine` formats the line from the rows :func:`pigp_torch.optimize` hands to its
``callback``; :func:`reporting_spec` wraps a benchmark :class:`~pigp_torch.bench.MethodSpec`
so that every ``tell`` of its optimizer prints the same line (how ``pigp demo`` shows its runs
without touching the benchmark's loop). A line looks like::

    evaluation   12/100  y = 1.2346 mA/min  best = 1.3457 mA/min  move 2.5 A (05G-QSS3)  0.84 s/step

The reading and the best are in the objective's unit; the
move is the largest absolute change of one knob from the previous evaluation (``-`` at the first
one), in the knobs' unit; the time is the wall time since the previous line (for the first line:
since the reporter was made).
"""

from __future__ import annotations

import contextlib
import dataclasses
import sys
import time
from collections.abc import Sequence

import torch

from pigp_torch._utils import DTYPE
from pigp_torch._utils.units import display_unit

_PRIOR_REJECTED = "physics prior rejected after "


def notice_text(message: str) -> str:
    """An optimizer's notice as the operator reads it.

    The prior check's rejection (``pigp-physics``) says in words what it means: the readings
    do not fit the physics form with the prior's peak (its misfit test, or a relaxed model with
    more evidence), because the machine is not the model ring the prior was built from; the
    method then moves to the named stage (a broader peak, or the peak's scale and background,
    then its eigen-scales and a wider centre, fitted from the readings instead of taken from the
    prior) and goes on. That is the method adapting as designed, not a fault of the machine or
    the run, and expected whenever the machine differs from the model (as in ``pigp demo``).
    Other notices pass unchanged."""
    if message.startswith(_PRIOR_REJECTED):
        rest = message[len(_PRIOR_REJECTED) :]
        return (
            "prior check: the readings disagree with the physics prior after "
            f"{rest}. Meaning: this machine differs from the model ring the prior was built "
            "from, so the method relaxes the prior as that stage says; expected when the "
            "machine is not the model (as in pigp demo), harmless, the run goes on"
        )
    return message


class ProgressLine:
    r"""Formats (and prints) one line per evaluation.

    Args:
        budget: ``M``, the evaluations of the run (start point included; > 0).
        knob_names: the knob columns of the rows (their order).
        maximize: direction of "best" (default: the largest reading).
        unit: knob unit printed after the move (``"A"`` on SPEAR3; default none), or one unit
            per knob (knobs of different kinds, e.g. a linac's k1 in 1/m^2 and angles in rad).
        objective_unit: unit of the readings (``"mA/min"`` for the loss rate; default none);
            they are printed in :func:`~pigp_torch._utils.units.display_unit`'s unit (a beam
            in m as µm).
        label: text put before the line (e.g. the method), default none.
        out: stream written to (default ``sys.stdout``); a closed stream is ignored.
        clock: seconds, for the time per step (default :func:`time.perf_counter`).

    Raises:
        ValueError: ``budget < 1`` or no knob names.
    """

    def __init__(
        self,
        budget: int,
        knob_names: Sequence[str],
        *,
        maximize: bool = True,
        unit: str | Sequence[str] = "",
        objective_unit: str = "",
        label: str = "",
        out=None,
        clock=time.perf_counter,
    ) -> None:
        if int(budget) < 1:
            raise ValueError(f"budget must be >= 1, got {budget}")
        self.budget = int(budget)
        self.knob_names = [str(n) for n in knob_names]
        if not self.knob_names:
            raise ValueError("no knob names")
        self.maximize = bool(maximize)
        per_knob = not isinstance(unit, str)
        self.unit = ", ".join(dict.fromkeys(map(str, unit))) if per_knob else str(unit)
        self.units = [str(u) for u in unit] if per_knob else [self.unit] * len(self.knob_names)
        if len(self.units) != len(self.knob_names):
            raise ValueError(f"{len(self.units)} knob units for {len(self.knob_names)} knobs")
        # readings shown in the unit a person reads (a beam in µm, not m); the best is kept raw
        self._y_scale, self.objective_unit = display_unit(str(objective_unit))
        self.label = str(label)
        self.out = out
        self._clock = clock
        self._last_time = clock()
        self.best: float | None = None
        self.previous: list[float] | None = None

    def seed(self, xs: Sequence[Sequence[float]], ys: Sequence[float]) -> None:
        """Take the evaluations of an earlier session (a resume): best and last point."""
        for y in ys:
            self._update_best(float(y))
        if len(xs):
            self.previous = [float(v) for v in xs[-1]]

    def _update_best(self, y: float) -> None:
        b = self.best
        if b is None or (y > b if self.maximize else y < b):
            self.best = y

    def format(self, step: int, x: Sequence[float], y: float) -> str:
        """The line of evaluation ``step`` (0-based) at ``x`` with reading ``y``; updates the
        best, the previous point and the clock."""
        x = [float(v) for v in x]
        self._update_best(float(y))
        now = self._clock()
        dt, self._last_time = now - self._last_time, now
        if self.previous is None or len(self.previous) != len(x):
            move = "move -"
        else:
            delta = (torch.tensor(x, dtype=DTYPE) - torch.tensor(self.previous, dtype=DTYPE)).abs()
            i = int(delta.argmax())
            unit = f" {self.units[i]}" if self.units[i] else ""
            move = f"move {float(delta[i]):.3g}{unit} ({self.knob_names[i]})"
        self.previous = x
        head = f"{self.label}  " if self.label else ""
        yu = f" {self.objective_unit}" if self.objective_unit else ""
        k = self._y_scale
        return (
            f"{head}evaluation {step + 1:>4}/{self.budget}  y = {k * y:.6g}{yu}  best = "
            f"{k * self.best:.6g}{yu}  {move}  {dt:.2f} s/step"
        )

    def __call__(self, row: dict) -> None:
        """:func:`pigp_torch.optimize` callback: print the line of one table row."""
        line = self.format(int(row["step"]), [row[n] for n in self.knob_names], float(row["y"]))
        for message in row.get("notices", ()):  # the optimizer's findings, e.g. a prior rejected
            line += f"\n{self.label + '  ' if self.label else ''}NOTICE  {notice_text(message)}"
        with contextlib.suppress(OSError, ValueError):  # a closed terminal never stops a run
            print(line, file=self.out or sys.stdout, flush=True)


class _ReportingBuilder:
    """Picklable builder of :func:`reporting_spec` (runs in worker processes too)."""

    def __init__(
        self, build, name: str, budget: int, knob_names, unit: str, objective_unit: str = ""
    ) -> None:
        self.build, self.name, self.budget = build, name, int(budget)
        self.knob_names, self.unit = list(knob_names), unit
        self.objective_unit = objective_unit

    def __call__(self, ctx, **options):
        optimizer = self.build(ctx, **options)
        line = ProgressLine(
            self.budget,
            self.knob_names,
            maximize=optimizer.maximize,
            unit=self.unit,
            objective_unit=self.objective_unit,
            label=f"{self.name:>14}",
        )
        tell = optimizer.tell

        seen = [0]

        def tell_and_report(x, y):
            tell(x, y)
            step = optimizer.n_told - 1
            text = line.format(step, torch.as_tensor(x, dtype=DTYPE).reshape(-1).tolist(), y)
            for notice in optimizer.notices[seen[0] :]:
                text += f"\n{line.label}  NOTICE  {notice_text(notice['message'])}"
            seen[0] = len(optimizer.notices)
            with contextlib.suppress(OSError, ValueError):  # a closed terminal
                print(text, file=sys.stdout, flush=True)

        optimizer.tell = tell_and_report
        return optimizer


def reporting_spec(
    spec, budget: int, knob_names: Sequence[str], *, unit: str = "", objective_unit: str = ""
):
    r"""A copy of the benchmark method ``spec`` whose optimizer prints a :class:`ProgressLine`
    (labelled with the method's name; knob moves in ``unit``, readings in ``objective_unit``) to
    stdout after every ``tell``.

    The optimizer is the one ``spec`` builds, unchanged (same class, name, seed and proposals);
    only its instance's ``tell`` is wrapped, so the run's numbers are those of ``spec``. The
    optimizer must count its tells (``n_told``, as every optimizer of the package does).
    """
    builder = _ReportingBuilder(spec.builder, spec.name, budget, knob_names, unit, objective_unit)
    return dataclasses.replace(spec, builder=builder)
