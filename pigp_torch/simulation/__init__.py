"""Alias: the storage-ring coupling simulation (lattice decks, seeded errors, the fast batched
model, the pyAT path) moved to the ring machine kind's folder, :mod:`pigp_torch.machines.ring`;
``pigp_torch.simulation.Spear3Coupling`` and the rest of this package's names, and each moved
module at its old path (``pigp_torch.simulation.spec``, ... as the moved module itself), still
import. ``pigp_torch.simulation.ares`` is the ARES-EA kind's simulation (its own alias)."""

from pigp_torch._utils.aliases import alias_package
from pigp_torch.machines.ring.calibration import calibrate_loss_rate_map
from pigp_torch.machines.ring.lattice import load_ring
from pigp_torch.machines.ring.ring import TARGET_RATIO, CouplingResult, RingCoupling
from pigp_torch.machines.ring.spear3 import LOSS_RATE_MAP, SKEW_K_PER_A_M2, Spear3Coupling

alias_package(__name__, "pigp_torch.machines.ring")

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
