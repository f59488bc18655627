"""Alias: the ARES-EA benchmark moved to the ARES-EA machine kind's folder,
:mod:`pigp_torch.machines.ares_ea.benchmark`; this module keeps the old import path working."""

from pigp_torch.machines.ares_ea.benchmark import (
    DEFAULT_ARES_METHODS,
    STEP_COLUMNS,
    THRESHOLDS_M,
    check_ares_methods,
    default_ares_methods,
    format_summary,
    plot_mae_vs_step,
    run_ares_benchmark,
    run_ares_trial,
    score_runs,
    summarize_scores,
)

__all__ = [
    "DEFAULT_ARES_METHODS",
    "STEP_COLUMNS",
    "THRESHOLDS_M",
    "check_ares_methods",
    "default_ares_methods",
    "format_summary",
    "plot_mae_vs_step",
    "run_ares_benchmark",
    "run_ares_trial",
    "score_runs",
    "summarize_scores",
]
