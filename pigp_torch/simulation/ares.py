"""Alias: the ARES-EA Cheetah simulation moved to the ARES-EA machine kind's folder,
:mod:`pigp_torch.machines.ares_ea.simulation`; this module keeps the old import path working."""

from pigp_torch.machines.ares_ea.simulation import (
    INCOMING_NAMES,
    KNOB_NAMES,
    KNOB_UNITS,
    MISALIGNMENT_NAMES,
    OBSERVABLE_NAMES,
    START_SETTING,
    AresSegment,
    AresTrial,
    default_trials_path,
    knob_bounds,
    load_lattice,
    load_trials,
    parse_trial_ids,
    screen_half_size,
)

__all__ = [
    "INCOMING_NAMES",
    "KNOB_NAMES",
    "KNOB_UNITS",
    "MISALIGNMENT_NAMES",
    "OBSERVABLE_NAMES",
    "START_SETTING",
    "AresSegment",
    "AresTrial",
    "default_trials_path",
    "knob_bounds",
    "load_lattice",
    "load_trials",
    "parse_trial_ids",
    "screen_half_size",
]
