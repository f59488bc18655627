"""Alias: the storage-ring coupling simulation (lattice decks, seeded errors, the fast batched
model, the pyAT path) moved to the ring machine kind's folder, :mod:`pigp_torch.machines.ring`;
this package keeps the old import paths working (``pigp_torch.simulation.Spear3Coupling``, and
one alias module per moved module)."""

from pigp_torch.machines.ring.calibration import calibrate_loss_rate_map
from pigp_torch.machines.ring.coupling import TARGET_RATIO, CouplingResult, RingCoupling
from pigp_torch.machines.ring.lattice import load_ring
from pigp_torch.machines.ring.spear3 import LOSS_RATE_MAP, SKEW_K_PER_A_M2, Spear3Coupling

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
