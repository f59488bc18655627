"""The "spear3-13" benchmark: methods x simulated machines, noise-free scores, summary, figures."""

from pigp_torch.benchmark.archive import machine_archive
from pigp_torch.benchmark.figures import plot_prior_mean, plot_runs
from pigp_torch.benchmark.protocol import (
    NOISE,
    machine_optimum,
    model_prior,
    run_benchmark,
    run_one,
    run_seed,
    score_run,
)
from pigp_torch.benchmark.scoring import first_moves, run_scores, summarize
from pigp_torch.methods import BO_DEFAULTS, DEFAULT_BUDGETS, METHODS, MethodSpec, RunContext

__all__ = [
    "BO_DEFAULTS",
    "DEFAULT_BUDGETS",
    "METHODS",
    "NOISE",
    "MethodSpec",
    "RunContext",
    "first_moves",
    "machine_archive",
    "machine_optimum",
    "model_prior",
    "plot_prior_mean",
    "plot_runs",
    "run_benchmark",
    "run_one",
    "run_scores",
    "run_seed",
    "score_run",
    "summarize",
]
