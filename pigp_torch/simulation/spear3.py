"""Alias: the ring's spear3 module moved to the ring machine kind's folder,
:mod:`pigp_torch.machines.ring.spear3`; this module keeps the old import path working."""

from pigp_torch.machines.ring.spear3 import (
    KNOB_LIMIT_A,
    KNOB_SETS,
    LOSS_RATE_MAP,
    SKEW_K_PER_A_M2,
    Spear3Coupling,
    knob_calibration_for,
    knob_names_for,
)

__all__ = [
    "KNOB_LIMIT_A",
    "KNOB_SETS",
    "LOSS_RATE_MAP",
    "SKEW_K_PER_A_M2",
    "Spear3Coupling",
    "knob_calibration_for",
    "knob_names_for",
]
