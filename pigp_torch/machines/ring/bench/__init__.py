"""The ring's benchmark, "spear3-13" (``pigp bench spear3``, ``pigp compare``): methods x simulated
machines, noise-free scores, summary and figures (:mod:`.protocol`, :mod:`.scoring`,
:mod:`.figures`), its machines and families (:mod:`.machines`, :mod:`.families`,
:mod:`.mismatch`), the oracle (:mod:`.oracle`), the ML-II archive (:mod:`.archive`), the job runner
(:mod:`.distributed`) and ``pigp demo`` (:mod:`.demo`, :mod:`.demo_cache`). The ``benchmarks/``
scripts at the top level are studies that use it; :mod:`pigp_torch.bench` keeps its old paths."""

from pigp_torch.machines.ring.bench.archive import machine_archive
from pigp_torch.machines.ring.bench.figures import plot_prior_mean, plot_runs
from pigp_torch.machines.ring.bench.protocol import (
    NOISE,
    machine_optimum,
    model_prior,
    run_benchmark,
    run_one,
    run_seed,
    score_run,
)
from pigp_torch.machines.ring.bench.scoring import first_moves, run_scores, summarize
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
