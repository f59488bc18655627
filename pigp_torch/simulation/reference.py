"""Alias: the ring's reference module moved to the ring machine kind's folder,
:mod:`pigp_torch.machines.ring.reference`; this module keeps the old import path working."""

from pigp_torch.machines.ring.reference import (
    cumulative_matrices,
    envelope_at,
    mode_emittances,
    observation_points,
    set_knobs,
    thin_knob_generator,
)

__all__ = [
    "cumulative_matrices",
    "envelope_at",
    "mode_emittances",
    "observation_points",
    "set_knobs",
    "thin_knob_generator",
]
