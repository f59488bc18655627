"""Machines behind one interface: set knobs, read the objective, get the current knobs."""

from pigp_torch.machine.base import (
    GuardedMachine,
    Machine,
    check_setting,
    max_step_tensor,
    ramp,
)
from pigp_torch.machine.epics import EpicsMachine
from pigp_torch.machine.errors import MachineError, PutRefused, ReadbackError, ReadError
from pigp_torch.machine.simulated import SimulatedMachine

__all__ = [
    "EpicsMachine",
    "GuardedMachine",
    "Machine",
    "MachineError",
    "PutRefused",
    "ReadError",
    "ReadbackError",
    "SimulatedMachine",
    "check_setting",
    "max_step_tensor",
    "ramp",
]
