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
