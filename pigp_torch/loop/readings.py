r"""Which readings a run believes: finite, inside the objective's physical range, and — when one
stands out from the run's own readings — confirmed by a re-read (:class:`ReadingJudge`); and the
reading loop that applies it (:func:`plausible_reading`).

**The rule.** Let :math:`y_1, \dots, y_n` be the readings accepted so far in the run (replayed
ones included), :math:`\tilde y` their median, :math:`\mathrm{MAD}` their median absolute
deviation and :math:`\sigma` the stated noise of one reading (objective units; ``None``: not
stated). A new reading :math:`y` is

* *invalid* — discarded, logged, read again — if it is not finite or lies outside the physical
  range :math:`[\ell, h]` (``objective_range``);
* *suspicious* if :math:`|y - \tilde y| > k\, s` with the robust scale
  :math:`s = \max(\sigma, 1.4826\,\mathrm{MAD})` and :math:`k` = :data:`OUTLIER_K` (= 5),
  once :math:`n \ge` :data:`MIN_READINGS` (= 5), and with :math:`s = \sigma` from the second
  reading until then; the run's *first* reading (:math:`n = 0`, nothing to compare it with) is
  always suspicious. The rule needs the stated noise: without :math:`\sigma` it does not apply
  (only finite and in range; a run without stated noise reads exactly as before). A suspicious
  reading is read again at the same setting and kept
  only if the two agree, :math:`|y - y'| \le a\sqrt 2\, \sigma` with :math:`a` =
  :data:`AGREE_A` (= 4); the evaluation's value is then their mean. If they do not agree, the
  re-read is judged afresh: not suspicious, it is the reading and the suspicious one is
  discarded (logged); suspicious too, it waits as well and the next reading that agrees with
  either decides (all within ``read_retries``).

A reading far from the others is not discarded for being far — a run that optimizes moves its
readings by many noise sigmas — only for not repeating: a genuine improvement reads the same
twice, a glitch does not. A glitch that repeats on consecutive readings with the same value
cannot be told from a real change by readings alone; the physical range is one defence against
those, and with ``restore: best`` two more readings-based checks come before the knobs are
left at the best point :math:`x^*` (logged value :math:`y^*`):

* **Control reading** (:func:`check_readings` at the reference): the knobs are first ramped
  to the run's first evaluation :math:`x_0` (usually the initial setpoints, where the restore
  ends anyway) and :data:`CONTROL_READS` fresh readings are compared with its logged value
  :math:`y_0`; they must agree within :math:`C s \sqrt{1 + 1/m}` in either direction. If they
  do not, the machine or its instrument changed during the run (a sustained glitch, a drift):
  the best is not trusted, the run says so and restores the initial knobs.
* **Confirmation** (:func:`confirm_best`): at :math:`x^*`, :data:`CONFIRM_READS` fresh
  readings must agree with :math:`y^*` within :math:`s(\sqrt{2 \ln N} + C\sqrt{1 + 1/m})` in
  EITHER direction (a best that reads far better than logged is not the point that was
  measured either), and, with :math:`\sigma` stated, with each other: their range
  :math:`\max - \min \le a\sqrt 2\,\sigma`. Otherwise the run restores the initial knobs.
* **Not below the start** (:func:`below_start`): the mean of those fresh readings must not be
  worse than the control reading's at :math:`x_0` (lower when maximizing, higher when
  minimizing): the knobs are never left at a point that reads worse than where the run began.

A rejected best is not reported as the run's best (the end record names it ``rejected_best``).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

import torch

from pigp_torch.machine.errors import ReadError, SeverityError

#: Outlier threshold :math:`k` in robust-scale units.
OUTLIER_K = 5.0
#: Agreement of a re-read with a suspicious reading, :math:`a` in units of :math:`\sqrt2\,s'`.
AGREE_A = 4.0
#: Accepted readings before the median/MAD rule applies on its own scale.
MIN_READINGS = 5
#: Consistency constant of the MAD for a Gaussian (MAD x 1.4826 estimates sigma).
MAD_TO_SIGMA = 1.4826


class ReadingJudge:
    r"""Keeps the run's accepted readings and says whether a new one is valid, suspicious, or
    agrees with a re-read (the rule in the module docstring).

    Args:
        noise: stated noise :math:`\sigma` of one reading (objective units, > 0), or ``None``.
        objective_range: ``(lower, upper)`` physical range of a reading, or ``None``.
        readings: readings accepted before (a resumed run's), in order.
    """

    def __init__(self, noise=None, objective_range=None, readings=()) -> None:
        self.noise = None if noise is None else float(noise)
        if self.noise is not None and not (0.0 < self.noise < math.inf):
            raise ValueError(f"noise must be positive and finite, got {noise}")
        if objective_range is not None:
            lo, hi = (float(v) for v in objective_range)
            if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
                raise ValueError(f"objective_range must be finite with lower < upper, got "
                                 f"{objective_range}")  # fmt: skip
            objective_range = (lo, hi)
        self.objective_range = objective_range
        self.readings: list[float] = [float(y) for y in readings]

    def accept(self, y: float) -> None:
        self.readings.append(float(y))

    def invalid(self, y: float) -> str | None:
        """Why ``y`` is invalid (not finite, outside the range), ``None`` if it is not."""
        if not math.isfinite(y):
            return f"non-finite reading {y}"
        if self.objective_range is not None:
            lo, hi = self.objective_range
            if not lo <= y <= hi:
                return f"reading {y:.6g} outside the objective range [{lo:g}, {hi:g}]"
        return None

    def invalid_parts(self, parts) -> str | None:
        """Why a reading averaged from ``parts`` is invalid: one of them is (an average would
        dilute a glitch into the range), ``None`` if none is."""
        for k, part in enumerate(parts or ()):
            why = self.invalid(float(part))
            if why is not None:
                return f"{why} (reading {k + 1} of {len(parts)} averaged)"
        return None

    def scale(self) -> float | None:
        r""":math:`s = \max(\sigma, 1.4826\,\mathrm{MAD})` (``None`` while the rule does not
        apply)."""
        n = len(self.readings)
        if self.noise is None or n == 0:
            return None
        if n >= MIN_READINGS:
            y = torch.tensor(self.readings, dtype=torch.float64)
            return max(float((y - y.median()).abs().median()) * MAD_TO_SIGMA, self.noise)
        return self.noise

    def suspicious(self, y: float) -> str | None:
        """Why ``y`` needs a re-read (far from the median of the accepted readings)."""
        if self.noise is not None and not self.readings:
            return "the run's first reading: nothing to compare it with yet"
        s = self.scale()
        if s is None:
            return None
        med = float(torch.tensor(self.readings, dtype=torch.float64).median())
        if abs(y - med) > OUTLIER_K * s:
            return (
                f"reading {y:.6g} is {abs(y - med) / s:.3g} robust sigmas (s = {s:.3g}) from the "
                f"median {med:.6g} of the run's {len(self.readings)} readings"
            )
        return None

    def agreement_tolerance(self) -> float:
        r""":math:`a\sqrt2\,\sigma`: how far a re-read may lie from a suspicious reading."""
        return AGREE_A * math.sqrt(2.0) * (self.noise or 0.0)


def _why_invalid(y: float, judge: ReadingJudge | None, parts) -> str | None:
    """Why the reading ``y`` (and the single readings ``parts()`` averaged into it) is invalid,
    or ``None``; without a judge only a non-finite reading is."""
    if judge is not None:
        why = judge.invalid(y)
        if why is None and parts is not None:
            why = judge.invalid_parts(parts())
        return why
    return None if math.isfinite(y) else f"non-finite reading {y}"


def plausible_reading(
    take: Callable[[], float | None],
    judge: ReadingJudge | None,
    retries: int,
    interval: float,
    on_discard: Callable[[str, float], None],
    parts: Callable[[], list | None] | None = None,
) -> tuple[float, int]:
    r"""A reading the run believes: ``take()`` until one is valid and (if suspicious) confirmed.

    ``take()`` returns one reading, or ``None`` for a reading it discarded itself (reported
    already), or raises ``ReadError``/``TimeoutError`` (a failed attempt; a ``SeverityError``
    reported to ``on_discard``) or ``MachineError`` (passed on). A reading invalid under
    ``judge`` is reported to ``on_discard(reason, y)`` (NaN/inf quietly), a failed attempt. A
    suspicious reading waits for a re-read: a later valid reading that agrees with it confirms
    it (the value is their mean; other waiting readings are discarded); one not suspicious
    itself is kept and the waiting ones are discarded; one suspicious agreeing with none waits
    too, a failed attempt. At most ``retries`` failed attempts (``interval`` s apart), so at
    most ``retries + 2`` reads. ``parts()`` (if given): the single readings a machine averaged
    into the last one; each must be valid too.

    Returns:
        ``(y, reads)``: the value and the readings taken.

    Raises:
        ReadError: more than ``retries`` failed attempts (``SeverityError``, with their count,
            when all were for a PV's alarm severity).
    """
    problems: list[str] = []
    failures = reads = 0
    pending: list[tuple[float, str]] = []  # suspicious readings waiting for a re-read
    alarms: list[BaseException] = []  # the errors of the reads that raised

    def drop_pending(keep=None, detail: str = "") -> None:
        for y_p, why in pending:
            if keep is None or y_p != keep:
                on_discard(f"{why}; not confirmed{detail}", y_p)
                problems.append(f"unconfirmed reading {y_p:.6g}")

    while failures <= retries:
        if reads > 0 and interval > 0 and not pending:
            time.sleep(interval)
        reads += 1
        try:
            y = take()
        except (ReadError, TimeoutError) as err:  # other MachineErrors end the reading
            failures += _failed_read(err, problems, alarms, on_discard)
            continue
        if y is None:
            problems.append("discarded")
            failures += 1
            continue
        y = float(y)
        why = _why_invalid(y, judge, parts)
        if why is not None:
            if math.isfinite(y):  # NaN/inf are retried quietly, as they always were
                on_discard(why, y)
            problems.append(why)
            failures += 1
            continue
        if pending:
            tol = judge.agreement_tolerance()
            match = next((p for p, _ in pending if abs(y - p) <= tol), None)
            if match is not None:
                drop_pending(keep=match, detail=f": a re-read agreed with {match:.6g} instead")
                value = 0.5 * (match + y)
                judge.accept(value)
                return value, reads
        why = judge.suspicious(y) if judge is not None else None
        if why is None:
            drop_pending(detail=f": the re-read {y:.6g} differs by more than "
                                f"{judge.agreement_tolerance() if judge else 0.0:.3g}")  # fmt: skip
            if judge is not None:
                judge.accept(y)
            return y, reads
        if pending:
            failures += 1  # two suspicious readings that disagree
        pending.append((y, why))
    drop_pending(detail=": no re-read agreed")
    raise _no_valid_reading(retries, failures, problems, alarms)


def _failed_read(err, problems: list, alarms: list, on_discard) -> int:
    """A read that raised: noted (returns 1, a failed attempt); an objective reading refused for
    its alarm severity is reported to ``on_discard`` with its value."""
    problems.append(f"{type(err).__name__}: {err}")
    alarms.append(err)
    value = err.value if isinstance(err, SeverityError) else None
    if value is not None and math.isfinite(value):
        on_discard(str(err), float(value))
    return 1


def _no_valid_reading(retries: int, failures: int, problems: list, alarms: list) -> ReadError:
    """The error of a reading that failed every attempt: a ``SeverityError`` naming the PV when
    every failed attempt was refused for its severity (the PV stays in alarm), else a
    ``ReadError`` listing the problems."""
    if len(alarms) == failures and all(isinstance(e, SeverityError) for e in alarms):
        last = alarms[-1]
        return SeverityError(last.pv, last.severity, last.value, repeated=len(alarms))
    return ReadError(f"no valid reading in {retries + 1} attempts ({'; '.join(problems)})")


#: Fresh readings taken at the best point before the knobs are left there (``restore: best``).
CONFIRM_READS = 3
#: Fresh readings taken at the reference (the run's first evaluation) before that.
CONTROL_READS = 1
#: Agreement of fresh readings with a logged one: :math:`s(\sqrt{2\ln N} + C\sqrt{1 + 1/m})`
#: (the selection term only for the best), :math:`C` this.
CONFIRM_C = 4.0


def check_readings(
    take: Callable[[], float],
    y_logged: float,
    judge: ReadingJudge | None,
    n: int,
    *,
    selection: bool,
) -> dict:
    r"""Read ``n`` times (``take()``, the knobs already at the point) and say whether the fresh
    readings reproduce the logged value ``y_logged`` of that point.

    With :math:`\bar y` the mean of the :math:`m = n` fresh readings and :math:`N` the run's
    readings, they agree if

    .. math:: |\bar y - y_\mathrm{logged}| \le s \left(\delta\sqrt{2 \ln N}
              + C \sqrt{1 + 1/m}\right), \qquad C = 4,

    (:math:`\delta = 1` with ``selection``: the best of :math:`N` noisy readings is read high by
    up to about :math:`\sqrt{2\ln N}\,s`; the second term is the spread of the difference) and,
    with the noise stated and :math:`m \ge 2`, if their range is at most
    :math:`a\sqrt2\,\sigma` (:data:`AGREE_A`). :math:`s` is the stated noise :math:`\sigma`;
    without it, the larger of :math:`1.4826\,\mathrm{MAD}` of the run's readings and the
    standard deviation of the fresh ones (a rough scale: state the noise with
    ``restore="best"``).

    Returns:
        ``{"confirmed", "readings", "mean", "best", "tolerance", "spread", "message"}``
        (``"best"`` is ``y_logged``); ``"abandoned"`` when a second signal
        (``KeyboardInterrupt``) stopped it, ``"error"`` when a reading failed (then not
        confirmed).
    """
    readings: list[float] = []
    out = {"confirmed": False, "readings": readings, "best": float(y_logged)}
    try:
        for _ in range(n):
            readings.append(float(take()))
    except KeyboardInterrupt as err:
        out.update(abandoned=True, message=f"stopped by a signal while reading it: {err}")
        return out
    except Exception as err:
        out.update(error=f"{type(err).__name__}: {err}", message=f"no reading there ({err})")
        return out
    run = list(judge.readings) if judge is not None else []
    stated = judge is not None and judge.noise is not None
    if stated:
        s = judge.noise
    else:
        s = float(torch.tensor(readings, dtype=torch.float64).std()) if n >= 2 else 0.0
        if len(run) >= 2:
            y = torch.tensor(run, dtype=torch.float64)
            s = max(s, float((y - y.median()).abs().median()) * MAD_TO_SIGMA)
    sel = math.sqrt(2.0 * math.log(len(run))) if selection and len(run) >= 2 else 0.0
    tol = s * (sel + CONFIRM_C * math.sqrt(1.0 + 1.0 / n))
    mean = sum(readings) / n
    spread = max(readings) - min(readings)
    spread_tol = AGREE_A * math.sqrt(2.0) * s if stated and n >= 2 else math.inf
    off = abs(mean - y_logged)
    out.update(tolerance=tol, mean=mean, spread=spread)
    out["confirmed"] = bool(off <= tol and spread <= spread_tol)
    out["message"] = (
        f"{n} fresh reading(s) there average {mean:.6g} against the logged {y_logged:.6g} "
        f"(off by {off:.3g}, tolerance {tol:.3g}"
        + (f"; spread {spread:.3g}, tolerance {spread_tol:.3g})" if n >= 2 and stated else ")")
    )
    return out


def confirm_best(
    take: Callable[[], float],
    y_best: float,
    judge: ReadingJudge | None,
    maximize: bool,
    n: int = CONFIRM_READS,
) -> dict:
    r"""Read the best point again ``n`` times (``take()``, the knobs already there) and say
    whether it reproduces: :func:`check_readings` with the selection term, two-sided (the fresh
    readings may lie neither far below nor far above the best reading :math:`y^*`) and, with
    the noise stated, agreeing with each other. ``maximize`` (the optimizer's direction) only
    words the message. A glitch that became the best does not reproduce; a genuine best does.
    """
    out = check_readings(take, y_best, judge, n, selection=True)
    if "mean" in out:
        worse = (y_best - out["mean"]) if maximize else (out["mean"] - y_best)
        out["message"] += "; worse than the best" if worse > 0 else "; better than the best"
    return out


def below_start(confirmation: dict, control: dict | None, maximize: bool) -> str | None:
    r"""Why the best point must not be kept although it reproduced: the mean :math:`\bar y^*` of
    its fresh readings is worse than the mean :math:`\bar y_0` of the control reading at the
    start point (:math:`\bar y^* < \bar y_0` when maximizing, :math:`>` when minimizing);
    ``None`` when it is not, or when either has no mean (no control reading: the best is the
    start point). Adds ``"control_mean"`` and ``"not_below_start"`` to ``confirmation``."""
    if control is None or "mean" not in control or "mean" not in confirmation:
        return None
    best, start = float(confirmation["mean"]), float(control["mean"])
    worse = (start - best) if maximize else (best - start)
    confirmation["control_mean"] = start
    confirmation["not_below_start"] = bool(worse <= 0)
    if worse <= 0:
        return None
    side = "below" if maximize else "above"
    return (
        f"its {len(confirmation['readings'])} fresh reading(s) average {best:.6g}, {side} the "
        f"control reading {start:.6g} at the start point (by {worse:.3g})"
    )
