"""Alias: the ring's linear_model module moved to the ring machine kind's folder,
:mod:`pigp_torch.machines.ring.linear_model`; this module keeps the old import path working."""

from pigp_torch.machines.ring.linear_model import (
    DAMPING_EXPONENT,
    RESIDUAL_TOL,
    BeamState,
    SegmentModel,
    doubling_count,
    equilibrium,
    equilibrium_chunked,
)

__all__ = [
    "DAMPING_EXPONENT",
    "RESIDUAL_TOL",
    "BeamState",
    "SegmentModel",
    "doubling_count",
    "equilibrium",
    "equilibrium_chunked",
]
