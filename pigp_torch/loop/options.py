r"""The safety options of a run (:class:`RunOptions`), checked once when they are made."""

from __future__ import annotations

import math
from dataclasses import dataclass

RESTORE_MODES = ("initial", "best", "none")
#: Readings a noise measurement may take (``noise_reads``, when not 0).
NOISE_READS = (3, 50)


@dataclass(frozen=True)
class RunOptions:
    r"""How :func:`~pigp_torch.loop.optimize` treats a machine: the safety rules of
    :mod:`pigp_torch.loop` (defaults: the safe choices). Every proposal is reached by the
    checked ramp of rule 2 (a move within the step limit, or with no limit, is one ``set``).

    Attributes:
        restore: ``"initial"`` (default), ``"best"`` or ``"none"``: where the knobs go at the end
            of a completed run (after a failure always to the initial knobs, unless ``"none"``).
        max_step: a step limit of the loop on top of the machine's ``max_step`` (scalar fraction
            of each knob's half-range or ``d`` absolute, see
            :func:`~pigp_torch._utils.max_step_tensor`), or ``None``.
        read_retries: extra read attempts after an invalid reading (>= 0; default 2).
        retry_interval: seconds to wait before each extra attempt (>= 0; default 0).
        objective_floor: abort when a reading falls below this value (``None``: no floor).
        handle_signals: turn SIGTERM and SIGHUP into :class:`~pigp_torch.loop.Terminated` during
            the run, and defer SIGINT/SIGTERM/SIGHUP while restoring (main thread only).
        readback_tol: allowed ``|get() - target|`` after a restore, a fraction of each knob's
            range (and around a reading, for a machine without a ``tolerance`` of its own;
            default 1e-3).
        restore_attempts: attempts at the restore (ramp and readback check, >= 1; default 3).
        restore_interval: seconds between those attempts (>= 0; default 1).
        restore_timeout: the restore's window (s, >= 0): attempts go on (``restore_interval``
            apart, at least 0.2 s) until ``restore_attempts`` were made *and* this many seconds
            passed since the first began, so an IOC that stalls or restarts within it is still
            restored (default 0: ``restore_attempts`` only; run files default to 30 s).
        check_readings: check every reading of a machine against its state (rule 3).
        noise: the stated noise :math:`\sigma` of one reading (objective units, > 0): with it
            a reading far from the run's own readings is re-read and kept only if it repeats
            (:mod:`~pigp_torch.loop.readings`); ``None`` (default): that rule is off.
        objective_range: ``(lower, upper)`` physical range of a reading; a reading outside it
            is discarded (``None``: the machine's ``objective_limits``, if any).
        noise_reads: with ``noise`` ``None`` on a machine, read the objective this many times
            at the setting found before the first evaluation and use their spread as the noise
            (:mod:`~pigp_torch.loop.noise`; a resume takes it from the log); 0 (default): no
            measurement, else 3 to 50.

    Raises:
        ValueError: a value out of its range (at construction).
    """

    restore: str = "initial"
    max_step: object = None
    read_retries: int = 2
    retry_interval: float = 0.0
    objective_floor: float | None = None
    handle_signals: bool = True
    readback_tol: float = 1e-3
    restore_attempts: int = 3
    restore_interval: float = 1.0
    restore_timeout: float = 0.0
    check_readings: bool = True
    noise: float | None = None
    objective_range: tuple[float, float] | None = None
    noise_reads: int = 0

    def __post_init__(self) -> None:
        if self.restore not in RESTORE_MODES:
            raise ValueError(f"restore must be one of {RESTORE_MODES}, got {self.restore!r}")
        if int(self.read_retries) != self.read_retries or self.read_retries < 0:
            raise ValueError(f"read_retries must be an integer >= 0, got {self.read_retries}")
        _finite_nonnegative("retry_interval", self.retry_interval)
        floor = self.objective_floor
        if floor is not None and not math.isfinite(float(floor)):
            raise ValueError(f"objective_floor must be finite or None, got {floor}")
        _finite_nonnegative("readback_tol", self.readback_tol)
        if int(self.restore_attempts) != self.restore_attempts or self.restore_attempts < 1:
            raise ValueError(
                f"restore_attempts must be an integer >= 1, got {self.restore_attempts}"
            )
        _finite_nonnegative("restore_interval", self.restore_interval)
        _finite_nonnegative("restore_timeout", self.restore_timeout)
        if self.noise is not None and not (0.0 < float(self.noise) < math.inf):
            raise ValueError(f"noise must be positive and finite or None, got {self.noise}")
        if self.objective_range is not None:
            lo, hi = (float(v) for v in self.objective_range)
            if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
                raise ValueError(
                    f"objective_range must be finite with lower < upper, got {self.objective_range}"
                )
            object.__setattr__(self, "objective_range", (lo, hi))
        n = self.noise_reads
        if int(n) != n or not (n == 0 or NOISE_READS[0] <= n <= NOISE_READS[1]):
            raise ValueError(f"noise_reads must be 0 or an integer in [{NOISE_READS[0]}, "
                             f"{NOISE_READS[1]}], got {n}")  # fmt: skip
        object.__setattr__(self, "noise_reads", int(n))
        object.__setattr__(self, "read_retries", int(self.read_retries))
        object.__setattr__(self, "retry_interval", float(self.retry_interval))
        object.__setattr__(self, "readback_tol", float(self.readback_tol))
        object.__setattr__(self, "restore_attempts", int(self.restore_attempts))
        object.__setattr__(self, "restore_interval", float(self.restore_interval))
        object.__setattr__(self, "restore_timeout", float(self.restore_timeout))


def _finite_nonnegative(name: str, value) -> None:
    if not (0.0 <= float(value) < float("inf")):
        raise ValueError(f"{name} must be finite and >= 0, got {value}")
