"""The library behind ``pigp bench``: the "spear3-13" benchmark (methods x simulated machines,
noise-free scores, summary, figures), the demo, and the BO speed and distributed runs (the
``benchmarks/`` scripts at the top level are studies that use it)."""

from pigp_torch.bench.archive import machine_archive
from pigp_torch.bench.figures import plot_prior_mean, plot_runs
from pigp_torch.bench.protocol import (
    NOISE,
    machine_optimum,
    model_prior,
    run_benchmark,
    run_one,
    run_seed,
    score_run,
)
from pigp_torch.bench.scoring import first_moves, run_scores, summarize
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
