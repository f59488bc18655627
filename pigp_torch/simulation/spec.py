"""Alias: the ring's spec module moved to the ring machine kind's folder,
:mod:`pigp_torch.machines.ring.spec`; this module keeps the old import path working."""

from pigp_torch.machines.ring.spec import (
    SPEAR3,
    RingSpec,
    as_ring_spec,
    knob_count,
)

__all__ = [
    "SPEAR3",
    "RingSpec",
    "as_ring_spec",
    "knob_count",
]
