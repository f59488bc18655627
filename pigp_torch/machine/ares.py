"""Alias: the simulated ARES-EA linac moved to the ARES-EA machine kind's folder,
:mod:`pigp_torch.machines.ares_ea.machine`; this module keeps the old import path working."""

from pigp_torch.machines.ares_ea.machine import (
    ARES_OBJECTIVES,
    AresMachine,
    ares_objective,
)

__all__ = [
    "ARES_OBJECTIVES",
    "AresMachine",
    "ares_objective",
]
