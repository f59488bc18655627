"""SPEAR3-like coupling simulation: ring builder, seeded errors, fast batched model, pyAT reference.

The only layer that imports pyAT. Main entry point: :class:`Spear3Coupling`.
"""

from pigp_torch.simulation.spear3 import (
    LOSS_RATE_MAP,
    TARGET_RATIO,
    CouplingResult,
    Spear3Coupling,
    calibrate_loss_rate_map,
)

__all__ = [
    "LOSS_RATE_MAP",
    "TARGET_RATIO",
    "CouplingResult",
    "Spear3Coupling",
    "calibrate_loss_rate_map",
]
