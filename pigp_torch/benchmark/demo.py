r"""The ``pigp demo`` pipeline: the main job end to end on the embedded simulated ring.

Simulated data of a model ring -> surrogate -> physics prior (cached between runs,
:mod:`~pigp_torch.benchmark.demo_cache`) -> the prior's error ensemble for the methods that use
it -> each method on a simulated machine with another error seed, scored as in the benchmark.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import pandas as pd
import torch

from pigp_torch.benchmark.demo_cache import DemoCache, default_cache_dir, with_cached_ensemble
from pigp_torch.benchmark.protocol import machine_loss_map, run_one
from pigp_torch.data.sampling import generate_dataset
from pigp_torch.loop.progress import reporting_spec
from pigp_torch.methods import METHODS
from pigp_torch.prior import prior_from_model
from pigp_torch.simulation.ensemble import (
    ENSEMBLE_SEED0,
    check_ensemble_size,
    with_center_ensemble,
)
from pigp_torch.simulation.spear3 import knob_names_for
from pigp_torch.simulation.spec import SPEAR3
from pigp_torch.surrogate import train_ensemble
from pigp_torch.surrogate.defaults import TRAIN_DEFAULTS


@dataclass(frozen=True)
class DemoSettings:
    """What ``pigp demo`` runs (the command's options; defaults are the command's).

    Attributes:
        model_seed: error seed of the model ring (data, surrogate, prior).
        machine_seed: error seed of the machine the methods run on.
        n: simulated samples of the model ring.
        members: surrogate networks.
        budget: evaluations per method.
        methods: benchmark method names.
        target: surrogate target.
        center_ensemble: ensemble rings for the methods that use the error ensemble (0: none).
        cache_dir: cache folder (``None``: :func:`default_cache_dir`).
        no_cache: read and write no cache.
    """

    model_seed: int = 0
    machine_seed: int = 1
    n: int = 100_000
    members: int = 3
    budget: int = 100
    methods: tuple[str, ...] = ("pigp-physics", "pigp", "ml2")
    target: str = TRAIN_DEFAULTS["target"]
    center_ensemble: int = 20
    cache_dir: Path | None = None
    no_cache: bool = False


def print_reports(reports) -> None:
    """One line per surrogate member: held-out errors."""
    for r in reports:
        print(f"      held-out rel. RMSE {100 * r['val_rel_rmse']:.2f} %, "
              f"near optimum {100 * r['near_opt_rel_rmse']:.2f} %")  # fmt: skip


def run_demo(a: DemoSettings) -> tuple[pd.DataFrame, object]:
    r"""Run the demo pipeline, printing its stages; returns the scored runs of every method (one
    table, :func:`~pigp_torch.benchmark.run_one`'s columns) and the physics prior used.

    It runs on one torch thread (restored afterwards), as the benchmark's runs do: a GP step is
    many small linear-algebra calls, and two OpenMP threads on a busy two-core machine spend
    their time waiting at barriers.

    Raises:
        ValueError: model and machine share a seed, either is among the ensemble seeds, a
            negative ensemble size, or an unknown method.
    """
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        return _run_demo(a)
    finally:
        torch.set_num_threads(threads)


def _run_demo(a: DemoSettings) -> tuple[pd.DataFrame, object]:
    if a.model_seed == a.machine_seed:
        raise ValueError("the model ring and the machine must have different error seeds")
    check_ensemble_size(a.center_ensemble, len(knob_names_for("paper13")))  # the demo's knobs
    if a.center_ensemble and {a.model_seed, a.machine_seed} & set(
        range(ENSEMBLE_SEED0, ENSEMBLE_SEED0 + a.center_ensemble)
    ):
        raise ValueError(
            f"--center-ensemble {a.center_ensemble} uses error seeds {ENSEMBLE_SEED0}..."
            f"{ENSEMBLE_SEED0 + a.center_ensemble - 1}: choose model and machine seeds "
            "outside them"
        )
    unknown = [m for m in a.methods if m not in METHODS]
    if unknown:
        raise ValueError(f"unknown method(s) {unknown}; known: {sorted(METHODS)}")
    cache = None if a.no_cache else DemoCache(a.cache_dir or default_cache_dir())
    key = {"model_seed": a.model_seed, "n": a.n, "members": a.members,
           "target": a.target, "noise": 0.04, "sample_seed": 0}  # fmt: skip
    model_ring = SPEAR3.build(a.model_seed)
    hit = None if cache is None else cache.load_prior(key)
    if hit is not None:
        prior, reports = hit
        print(f"[1-3/4] physics prior of the surrogate from the cache ({cache.path('prior', key)}"
              "; --no-cache recomputes it)", flush=True)  # fmt: skip
        print_reports(reports)
    else:
        print(f"[1/4] simulated data of the model ring (error seed {a.model_seed})", flush=True)
        data = generate_dataset(model_ring, a.n, seed=0, progress=True)
        print(f"[2/4] surrogate: {a.members} network(s) on {len(data)} samples", flush=True)
        surrogate, reports = train_ensemble(
            data, n_members=a.members, target=a.target, progress=True
        )
        print_reports(reports)
        print("[3/4] physics prior: optimum and Hessian of the surrogate", flush=True)
        prior = prior_from_model(
            surrogate,
            model_ring.bounds,
            f_inf=model_ring.loss_background,
            noise=0.04,
            knob_names=model_ring.knob_names,
            provenance={"surrogate_of": f"Spear3Coupling(error_seed={a.model_seed})"},
        )
        if cache is not None:
            cache.save_prior(key, prior, reports)
    print(f"      condition number {prior.condition_number:.0f}, surrogate optimum "
          f"{prior.f_x0:.3f} mA/min")  # fmt: skip
    if a.center_ensemble and any(METHODS[m].uses_center_ensemble for m in a.methods):
        meta = {"error_seed": a.model_seed}

        def compute(p):
            return with_center_ensemble(p, a.center_ensemble, meta, a.machine_seed, progress=True)

        prior, source = with_cached_ensemble(prior, a.center_ensemble, a.model_seed, cache, compute)
        if source is not None:
            print(f"      optima of {a.center_ensemble} ensemble rings from the cache "
                  f"({source})", flush=True)  # fmt: skip
    f_inf, g = machine_loss_map(a.machine_seed, model_ring.loss_rate_map)
    print(f"[4/4] {', '.join(a.methods)} on the benchmark's machine {a.machine_seed}, "
          f"{a.budget} evaluations each: coupling-error seed {a.machine_seed} with its own "
          f"loss-rate map (background {f_inf:.3f} mA/min, Touschek scale "
          f"x{g / model_ring.loss_rate_map[1]:.2f} of the model's); a run file reaches it with "
          f"machine: {{kind: sim, error_seed: {a.machine_seed}, loss_map: benchmark}}",
          flush=True)  # fmt: skip
    names, unit = model_ring.knob_names, model_ring.knob_units
    runs = [
        run_one(reporting_spec(METHODS[m], a.budget, names, unit=unit, objective_unit="mA/min"),
                a.machine_seed, prior, budget=a.budget)
        for m in a.methods
    ]  # fmt: skip
    return pd.concat(runs, ignore_index=True), prior
