"""Storage-ring coupling simulation: lattice decks, seeded errors, fast batched model, pyAT path.

The only layer that imports pyAT. Entry points: :class:`RingCoupling` (any ring and knobs) and
its SPEAR3 instance :class:`Spear3Coupling` (the real deck, knobs in amps).
"""

from pigp_torch.simulation.calibration import calibrate_loss_rate_map
from pigp_torch.simulation.lattice import load_ring
from pigp_torch.simulation.ring import TARGET_RATIO, CouplingResult, RingCoupling
from pigp_torch.simulation.spear3 import LOSS_RATE_MAP, SKEW_K_PER_A_M2, Spear3Coupling

__all__ = [
    "LOSS_RATE_MAP",
    "SKEW_K_PER_A_M2",
    "TARGET_RATIO",
    "CouplingResult",
    "RingCoupling",
    "Spear3Coupling",
    "calibrate_loss_rate_map",
    "load_ring",
]
