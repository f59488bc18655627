"""Alias: ``pigp bench ares`` moved to the ARES-EA machine kind's folder,
:mod:`pigp_torch.machines.ares_ea.command`; this module keeps the old import path working."""

from pigp_torch.machines.ares_ea.command import (
    ARES_PRIOR_METHODS_HELP,
    MODEL_ERROR_HELP,
    cmd_bench_ares,
    register,
)

__all__ = [
    "ARES_PRIOR_METHODS_HELP",
    "MODEL_ERROR_HELP",
    "cmd_bench_ares",
    "register",
]
