"""Alias: the ring's deck module moved to the ring machine kind's folder,
:mod:`pigp_torch.machines.ring.deck`; this module keeps the old import path working."""

from pigp_torch.machines.ring.deck import (
    DECKS,
    SPEAR3_ENERGY,
    deck_path,
    load_table,
    make_radiating,
    ring_from_table,
    ring_parameters,
    spear3_header,
    spear3_ring,
)

__all__ = [
    "DECKS",
    "SPEAR3_ENERGY",
    "deck_path",
    "load_table",
    "make_radiating",
    "ring_from_table",
    "ring_parameters",
    "spear3_header",
    "spear3_ring",
]
