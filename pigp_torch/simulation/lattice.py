"""Alias: the ring's lattice module moved to the ring machine kind's folder,
:mod:`pigp_torch.machines.ring.lattice`; this module keeps the old import path working."""

from pigp_torch.machines.ring.lattice import (
    fingerprint,
    insert_knobs,
    load_ring,
    resolve_knob,
)

__all__ = [
    "fingerprint",
    "insert_knobs",
    "load_ring",
    "resolve_knob",
]
