r"""Reading the objective PV of an :class:`~pigp_torch.machine.epics.EpicsMachine`: the mean of
``n_average`` readings, each fresh (a CA timestamp newer than the previous valid reading's, polled
every ``stale_poll`` s for at most ``stale_timeout`` s) and valid (finite, and its alarm
severity below ``refuse_severity``: ``INVALID`` by default, ``MAJOR`` too by option; up to
``read_retries`` retries ``retry_interval`` s apart); the knob readbacks and the observables
with their severities too. The rules in full: :mod:`pigp_torch.machine.epics`.
"""

from __future__ import annotations

import math
import time

from pigp_torch.machine.errors import SEVERITIES, MachineError, ReadError, SeverityError


class StaleReadingError(ReadError):
    """The objective PV's timestamp did not advance within ``stale_timeout`` (a frozen PV)."""


class ObjectiveReader:
    """The objective reads of :class:`~pigp_torch.machine.epics.EpicsMachine` (a mixin: it uses
    the machine's client ``_ca``, ``objective_pv``, ``observable_pvs``, ``timeout``, the read
    settings, the counters ``n_reads`` / ``n_invalid_readings``, ``_last_stamp``,
    ``refuse_severity`` and ``_check_open``)."""

    @staticmethod
    def _severity_level(refuse) -> int:
        """The lowest alarm severity refused: ``"INVALID"`` (3) or ``"MAJOR"`` (2)."""
        name = str(refuse).upper()
        if name not in SEVERITIES[2:]:
            raise ValueError(f"refuse_severity must be MAJOR or INVALID, got {refuse!r}")
        return SEVERITIES.index(name)

    def _read_knobs(self, refuse: bool = True) -> list[float]:
        """The knob readbacks (DBR_TIME reads). A readback whose severity is refused raises
        :class:`SeverityError` (``refuse``), or reads as NaN (the caller polls again)."""
        pairs = self._ca.read_alarmed(self.readback_pvs, self.timeout)
        values = []
        for pv, (value, severity) in zip(self.readback_pvs, pairs, strict=True):
            if severity >= self.refuse_severity:
                if refuse:
                    raise SeverityError(pv, severity)
                value = math.nan
            values.append(value)
        bad = [pv for pv, v in zip(self.readback_pvs, values, strict=True) if not math.isfinite(v)]
        if bad and refuse:
            raise MachineError(f"non-finite knob readbacks: {bad}")
        return values

    def _fresh_reading(self, info: dict) -> float:
        """One reading whose timestamp is newer than the previous valid one (polls while not).

        Raises:
            MachineError: the read failed.
            StaleReadingError: no newer timestamp within ``stale_timeout``.
        """
        deadline = time.monotonic() + self.stale_timeout
        while True:
            value, stamp, severity = self._ca.read_timed(self.objective_pv, self.timeout)
            if severity >= self.refuse_severity:  # not a valid reading, fresh or not
                kept = value if math.isfinite(value) else None
                refused = {"value": kept, "stamp": stamp, "severity": SEVERITIES[severity]}
                info.setdefault("refused", []).append(refused)
                raise SeverityError(self.objective_pv, severity, value)
            if self._last_stamp is None or stamp > self._last_stamp or not math.isfinite(value):
                break
            if time.monotonic() >= deadline:
                raise StaleReadingError(
                    f"{self.objective_pv} has not updated for {self.stale_timeout:g} s "
                    f"(timestamp {stamp:.6f} not newer than the previous reading's; "
                    "a frozen PV or a stopped IOC record)"
                )
            info["stale_polls"] += 1
            time.sleep(min(self.stale_poll, max(0.0, deadline - time.monotonic())))
        if math.isfinite(value):
            self._last_stamp = stamp
            info["stamps"].append(stamp)
            info["values"].append(value)
        return value

    def _one_reading(self, info: dict) -> float:
        """One valid, fresh reading of the objective PV, with up to ``read_retries`` retries."""
        reasons = []
        severity = None
        for attempt in range(self.read_retries + 1):
            if attempt > 0 and self.retry_interval > 0:
                time.sleep(self.retry_interval)
            try:
                value = self._fresh_reading(info)
            except StaleReadingError:
                self.n_invalid_readings += 1
                raise
            except MachineError as err:
                reasons.append(str(err))
                severity = err if isinstance(err, SeverityError) else None
            else:
                if math.isfinite(value):
                    self.n_reads += 1
                    return value
                reasons.append(f"non-finite value {value}")
            self.n_invalid_readings += 1
        if severity is not None:  # the last attempt read a refused severity: say so
            raise severity
        raise ReadError(
            f"no valid reading of {self.objective_pv} in {self.read_retries + 1} attempts: "
            + "; ".join(reasons)
        )

    def read(self) -> float:
        """Mean of ``n_average`` valid readings of the objective PV.

        Raises:
            ReadError: a reading was still invalid (NaN/inf, timeout, disconnected) after
                ``read_retries`` retries.
            StaleReadingError: the objective PV did not update within ``stale_timeout``.

        With observable PVs (``observable_pvs``) they are read once after the objective's
        readings and kept in ``last_observables`` (``None`` until a read succeeds); their
        timestamps are not checked.
        """
        self._check_open()
        info: dict = {"stamps": [], "values": [], "stale_polls": 0}
        self.last_reading = info
        self.last_observables = None  # never those of an earlier reading
        total = 0.0
        for k in range(self.n_average):
            if k > 0 and self.average_interval > 0:
                time.sleep(self.average_interval)
            total += self._one_reading(info)
        if self.observable_pvs:
            self.last_observables = self._read_observables()
        return total / self.n_average

    def _read_observables(self):
        """The observable PVs read once, after the objective's readings: ``m`` float64.

        Raises:
            ReadError: a PV could not be read or is not finite (the loop reads again).
        """
        import torch

        pvs = self.observable_pvs
        try:
            pairs = self._ca.read_alarmed(pvs, self.timeout)
        except MachineError as err:
            raise ReadError(f"observables: {err}") from err
        for pv, (_, severity) in zip(pvs, pairs, strict=True):
            if severity >= self.refuse_severity:
                raise SeverityError(pv, severity)
        values = [value for value, _ in pairs]
        bad = [pv for pv, v in zip(pvs, values, strict=True) if not math.isfinite(v)]
        if bad:
            raise ReadError(f"non-finite observable readings of {bad}")
        return torch.tensor(values, dtype=torch.float64)
