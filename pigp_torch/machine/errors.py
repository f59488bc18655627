"""Errors a machine raises when it cannot do what the loop asked.

The loop (:func:`pigp_torch.optimize`) treats every :class:`MachineError` as a reason to stop the
run and put the knobs back; a :class:`ReadError` (no valid objective reading after the machine's
own retries) and a :class:`ReadbackError` (a knob did not reach its setpoint) are the common cases.
"""

from __future__ import annotations


class MachineError(RuntimeError):
    """The machine could not carry out a set or a read (connection lost, timeout, ...)."""


class ReadError(MachineError):
    """No valid (finite, timely) objective reading after the allowed retries."""


class ReadbackError(MachineError):
    """A knob's readback did not reach its setpoint within the tolerance and time allowed."""


class PutRefused(MachineError):
    """The control system refused a put (e.g. a value outside the IOC's control limits
    DRVL/DRVH): the message names the PVs and the IOC's reason.

    Attributes:
        pvs: the PV names whose puts were refused.
    """

    def __init__(self, message: str, pvs=()) -> None:
        super().__init__(message)
        self.pvs = list(pvs)


#: EPICS alarm severities by value (``dbr_time`` ``severity``; pvAccess ``alarm.severity``).
SEVERITIES = ("NO_ALARM", "MINOR", "MAJOR", "INVALID")


class SeverityError(ReadError):
    r"""A PV was read with an alarm severity the machine refuses (``INVALID``; ``MAJOR`` too by
    option): the reading is not valid and is read again.

    Attributes:
        pv: the PV read.
        severity: its severity's name (one of :data:`SEVERITIES`; given as that name or its
            value 0 .. 3).
        value: the value read with it, for an objective reading (``None`` for a knob readback
            or an observable: not a reading of the objective).
        repeated: reads in a row that had it (said in the message when more than one).
    """

    def __init__(
        self, pv: str, severity: int | str, value: float | None = None, repeated: int = 1
    ) -> None:
        self.pv, self.value = str(pv), value
        if not isinstance(severity, str):  # a value: its name
            severity = SEVERITIES[int(severity)] if 0 <= int(severity) < 4 else str(severity)
        self.severity = severity
        shown = "" if value is None else f" (value {value:.6g})"
        times = f" on {repeated} reads in a row" if repeated > 1 else ""
        super().__init__(f"{pv} read with alarm severity {self.severity}{times}{shown}")
