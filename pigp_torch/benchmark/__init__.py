"""Alias: the first path of the library behind ``pigp bench`` (now :mod:`pigp_torch.bench`, the
BO speed run, and the ring's "spear3-13" benchmark in :mod:`pigp_torch.machines.ring.bench`);
``pigp_torch.benchmark``, its names and each of its modules (as the moved module itself) still
import, and so does ``pigp_torch.benchmark.ares`` (the ARES-EA benchmark, in its kind's folder)."""

from pigp_torch._utils.aliases import alias_package
from pigp_torch.machines.ring.bench import (
    BO_DEFAULTS,
    DEFAULT_BUDGETS,
    METHODS,
    NOISE,
    MethodSpec,
    RunContext,
    first_moves,
    machine_archive,
    machine_optimum,
    model_prior,
    plot_prior_mean,
    plot_runs,
    run_benchmark,
    run_one,
    run_scores,
    run_seed,
    score_run,
    summarize,
)

alias_package(__name__, "pigp_torch.bench")

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
