"""Alias: the ring's errors module moved to the ring machine kind's folder,
:mod:`pigp_torch.machines.ring.errors`; this module keeps the old import path working."""

from pigp_torch.machines.ring.errors import (
    CUT,
    QUAD_ROLL_RMS,
    SEXT_OFFSET_RMS,
    CouplingErrors,
    magnet_counts,
    magnets,
    truncated_normal,
)

__all__ = [
    "CUT",
    "QUAD_ROLL_RMS",
    "SEXT_OFFSET_RMS",
    "CouplingErrors",
    "magnet_counts",
    "magnets",
    "truncated_normal",
]
