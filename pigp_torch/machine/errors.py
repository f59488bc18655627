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
