"""Alias: the ring's ring module moved to the ring machine kind's folder,
:mod:`pigp_torch.machines.ring.coupling`; this module keeps the old import path working."""

from pigp_torch.machines.ring.coupling import (
    CHUNK,
    GPU_CHUNK,
    LOSS_RATE_ANCHOR,
    TARGET_RATIO,
    CouplingResult,
    RingCoupling,
)

__all__ = [
    "CHUNK",
    "GPU_CHUNK",
    "LOSS_RATE_ANCHOR",
    "TARGET_RATIO",
    "CouplingResult",
    "RingCoupling",
]
