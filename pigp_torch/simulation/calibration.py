"""Alias: the ring's calibration module moved to the ring machine kind's folder,
:mod:`pigp_torch.machines.ring.calibration`; this module keeps the old import path working."""

from pigp_torch.machines.ring.calibration import (
    MAP_SPREAD,
    MIN_BACKGROUND_SHARE,
    calibrate_error_scale,
    calibrate_loss_rate_map,
    machine_loss_map,
    peak_density,
)

__all__ = [
    "MAP_SPREAD",
    "MIN_BACKGROUND_SHARE",
    "calibrate_error_scale",
    "calibrate_loss_rate_map",
    "machine_loss_map",
    "peak_density",
]
