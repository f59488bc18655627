r"""The ``pigp demo`` pipeline: the main job end to end on the embedded simulated ring.

Simulated data of a model ring -> surrogate -> physics prior (cached between runs,
:mod:`~.demo_cache`) -> the prior's error ensemble for the methods that use
it -> each method on a simulated machine with another error seed, scored as in the benchmark.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import pandas as pd

from pigp_torch._utils.pool import (
    InlineExecutor,
    default_workers,
    job_pool,
    one_torch_thread,
    spread,
)
from pigp_torch.data.sampling import generate_dataset
from pigp_torch.loop.progress import reporting_spec
from pigp_torch.machines.ring.bench.demo_cache import (
    DemoCache,
    apply_cached_ensemble,
    default_cache_dir,
    ensemble_key,
)
from pigp_torch.machines.ring.bench.protocol import machine_loss_map, run_one
from pigp_torch.machines.ring.ensemble import (
    ENSEMBLE_SEED0,
    check_ensemble_size,
    ensemble_plan,
    gather_optima,
    ring_optima,
    with_center_ensemble,
)
from pigp_torch.machines.ring.spear3 import knob_names_for
from pigp_torch.machines.ring.spec import SPEAR3
from pigp_torch.methods import METHODS
from pigp_torch.prior import prior_from_model
from pigp_torch.surrogate import SurrogateEnsemble, train_surrogate
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
        workers: processes for the independent jobs (the surrogate's networks, the ensemble
            rings, the methods' runs; default :func:`~pigp_torch._utils.pool.default_workers`:
            the CPUs available, at most 2). The numbers do not depend on it.
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
    workers: int = field(default_factory=default_workers)


def print_reports(reports) -> None:
    """One line per surrogate member: held-out errors."""
    for r in reports:
        print(f"      held-out rel. RMSE {100 * r['val_rel_rmse']:.2f} %, "
              f"near optimum {100 * r['near_opt_rel_rmse']:.2f} %")  # fmt: skip


def run_demo(a: DemoSettings) -> tuple[pd.DataFrame, object]:
    r"""Run the demo pipeline, printing its stages; returns the scored runs of every method (one
    table, :func:`~.run_one`'s columns) and the physics prior used.

    It runs on one torch thread (restored afterwards), as the benchmark's runs do: a GP step is
    many small linear-algebra calls, and two OpenMP threads on a busy two-core machine spend
    their time waiting at barriers.

    Raises:
        ValueError: model and machine share a seed, either is among the ensemble seeds, a
            negative ensemble size, or an unknown method.
    """
    with one_torch_thread():
        return _run_demo(a)


#: CPU seconds of a process between two progress lines of the surrogate's training.
PROGRESS_EVERY_S = 5.0


class EpochLines:
    """The ``on_epoch`` of :func:`~pigp_torch.surrogate.train_surrogate` in the demo: a plain
    line (network k of K, epoch e of E, validation loss, seconds) after the first epoch, then
    after the first epoch that ends ``every`` s of this process's CPU time (``clock``, default
    :func:`time.process_time`) or ``wall_every`` s of wall time (``wall_clock``, default
    :func:`time.perf_counter`; a busy machine) after the last line, and after the last epoch.
    Plain lines, not a bar: they stay readable between the lines of a run on another process,
    and in a log file. Picklable (it runs in worker processes too)."""

    def __init__(
        self,
        member: int,
        members: int,
        every: float = PROGRESS_EVERY_S,
        wall_every: float = 6 * PROGRESS_EVERY_S,
        clock=None,
        wall_clock=None,
    ) -> None:
        self.member, self.members, self.every = int(member), int(members), float(every)
        self.wall_every = float(wall_every)
        self.clock, self.wall_clock = clock, wall_clock
        self._last: tuple[float, float] | None = None

    def __call__(self, r: dict) -> None:
        now = ((self.clock or time.process_time)(), (self.wall_clock or time.perf_counter)())
        due = self._last is None or r["epoch"] >= r["max_epochs"]
        cpu, wall = (now[0] - self._last[0], now[1] - self._last[1]) if not due else (0, 0)
        if not due and cpu < self.every and wall < self.wall_every:
            return
        self._last = now
        print(f"      network {self.member}/{self.members}: epoch {r['epoch']}/{r['max_epochs']}, "
              f"validation loss {r['val_loss']:.3g} (best {r['best_val_loss']:.3g} at epoch "
              f"{r['best_epoch']}), {r['elapsed_s']:.0f} s", flush=True)  # fmt: skip


def _train_member(data, seed: int, target: str, members: int):
    """One surrogate network (a job of :func:`~pigp_torch._utils.pool.job_pool`), with a
    progress line every :data:`PROGRESS_EVERY_S` s of CPU (:class:`EpochLines`)."""
    lines = EpochLines(seed + 1, members)
    return train_surrogate(data, seed=seed, target=target, progress=False, on_epoch=lines)


def _run_method(spec, machine_seed: int, prior, budget: int):
    """One method's run on the demo's machine (a job)."""
    return run_one(spec, machine_seed, prior, budget=budget)


def _check(a: DemoSettings) -> None:
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
    if int(a.workers) < 1:
        raise ValueError(f"--workers must be >= 1, got {a.workers}")


def _elapsed(t0: float) -> str:
    return f"{time.perf_counter() - t0:.0f} s"


def _run_demo(a: DemoSettings) -> tuple[pd.DataFrame, object]:
    _check(a)
    t_start = time.perf_counter()
    cache = None if a.no_cache else DemoCache(a.cache_dir or default_cache_dir())
    key = {"model_seed": a.model_seed, "n": a.n, "members": a.members,
           "target": a.target, "noise": 0.04, "sample_seed": 0}  # fmt: skip
    hit = None if cache is None else cache.load_prior(key)
    _print_start(a, None if hit is None else cache.path("prior", key))
    model_ring = SPEAR3.build(a.model_seed)
    names = list(model_ring.knob_names)
    want_ensemble = bool(a.center_ensemble) and any(
        METHODS[m].uses_center_ensemble for m in a.methods
    )
    ens_key = ensemble_key(a.model_seed, a.center_ensemble, names)
    ens_hit = None if cache is None or not want_ensemble else cache.load_ensemble(ens_key)
    unit = model_ring.knob_units
    specs = {m: reporting_spec(METHODS[m], a.budget, names, unit=unit, objective_unit="mA/min")
             for m in a.methods}  # fmt: skip
    with job_pool(a.workers) as pool:
        parallel = not isinstance(pool, InlineExecutor)
        # with a second process, a method that needs no prior (ML-II) starts there at once
        early = [m for m in a.methods if parallel and not specs[m].needs_prior]
        if early:
            print(f"      {', '.join(early)} needs no prior: its run (stage 4) starts now on a "
                  "second process, alongside the stages before it", flush=True)  # fmt: skip
        runs = dict(
            zip(early, spread(pool, _method_jobs(a, early, specs, None), set()), strict=True)
        )
        data = None
        if hit is None:
            t0 = time.perf_counter()
            data = generate_dataset(model_ring, a.n, seed=0, progress=True)
            print(f"      {len(data)} samples ({_elapsed(t0)})", flush=True)
            print(f"[2/4] surrogate: {a.members} network(s) on {len(data)} samples"
                  + (f", on {a.workers} processes" if parallel and not early else ""),
                  flush=True)  # fmt: skip
        t_train = time.perf_counter()
        jobs = [(_train_member, (data, k, a.target, a.members), {})
                for k in range(a.members if hit is None else 0)]  # fmt: skip
        # the caller trains every a.workers-th network (all of them while a spawned process runs
        # an early method); the others and the rings go to the pool
        local = set(range(0, len(jobs), 1 if early else a.workers))
        if want_ensemble and ens_hit is None:
            jobs, local = _ring_jobs(a, names, jobs, local, parallel)
        done = spread(pool, jobs, local)
        members = done[: a.members] if hit is None else []
        rings = done[len(members) :]
        prior = _surrogate_prior(a, hit, members, model_ring, cache, key, t_train)
        if want_ensemble:
            prior = _with_ensemble(a, prior, ens_hit, rings, cache, ens_key)
        late = [m for m in a.methods if m not in runs]
        _print_machine(a, model_ring, late, parallel)
        t0 = time.perf_counter()
        # the caller runs the last method (the baselines come last: they are the slowest)
        runs.update(zip(late, spread(pool, _method_jobs(a, late, specs, prior), {len(late) - 1}),
                        strict=True))  # fmt: skip
        table = pd.concat([runs[m].result() for m in a.methods], ignore_index=True)
    print(f"      runs done ({_elapsed(t0)}); the demo took {_elapsed(t_start)}", flush=True)
    return table, prior


def _print_start(a: DemoSettings, cached) -> None:
    """The first stage's line: stage 1 starts, or stages 1-3 come from the ``cached`` file."""
    if cached is None:
        print(f"[1/4] simulated data of the model ring (error seed {a.model_seed}): "
              f"{a.n} samples", flush=True)  # fmt: skip
    else:
        print(f"[1-3/4] physics prior of the surrogate from the cache ({cached}; --no-cache "
              "recomputes it)", flush=True)  # fmt: skip


def _method_jobs(a: DemoSettings, methods, specs, prior) -> list:
    return [(_run_method, (specs[m], a.machine_seed, prior, a.budget), {}) for m in methods]


def _ring_jobs(a: DemoSettings, names, jobs, local, parallel):
    """``jobs`` and ``local`` with the ensemble rings' jobs: one part per spawned process, and
    one for the caller if it has no network to train."""
    ring_model, seeds = ensemble_plan(
        a.center_ensemble, {"error_seed": a.model_seed}, names, a.machine_seed
    )
    print(f"      and the optima of {len(seeds)} ensemble rings (other error seeds) for the "
          "prior's centre and shape" + (", alongside" if parallel else ""), flush=True)  # fmt: skip
    n_parts = 1 if not parallel else a.workers - (1 if jobs else 0)
    part = -(-len(seeds) // n_parts)
    if not jobs and parallel:
        local = {0}
    ring_jobs = [(ring_optima, (seeds[i : i + part],), {"model": ring_model, "progress": True,
                  "first_index": i, "total": len(seeds)})
                 for i in range(0, len(seeds), part)]  # fmt: skip
    return jobs + ring_jobs, local


def _print_machine(a: DemoSettings, model_ring, methods, parallel: bool) -> None:
    f_inf, g = machine_loss_map(a.machine_seed, model_ring.loss_rate_map)
    print(f"[4/4] {', '.join(methods) or 'all methods started'} on the benchmark's machine "
          f"{a.machine_seed}, {a.budget} evaluations each: coupling-error seed {a.machine_seed} "
          f"with its own loss-rate map (background {f_inf:.3f} mA/min, Touschek scale "
          f"x{g / model_ring.loss_rate_map[1]:.2f} of the model's); a run file reaches it with "
          f"machine: {{kind: sim, error_seed: {a.machine_seed}, loss_map: benchmark}}"
          + (f"; {a.workers} runs at a time" if parallel else ""), flush=True)  # fmt: skip
    if any(METHODS[m].needs_prior for m in a.methods):
        print(f"      the prior is the model ring's (error seed {a.model_seed}), not this "
              "machine's: a NOTICE that the readings disagree with the physics prior is "
              "expected here (pigp-physics then relaxes its prior and goes on)",
              flush=True)  # fmt: skip


def _surrogate_prior(a, hit, members, model_ring, cache, key, t0):
    """Stages 1-3: the cached prior, or the trained members' ensemble and its prior."""
    if hit is not None:
        prior, reports = hit
        print_reports(reports)
    else:
        trained = [m.result() for m in members]
        reports = [r for _, r in trained]
        print_reports(reports)
        print(f"      stage 2 done ({_elapsed(t0)})", flush=True)
        surrogate = SurrogateEnsemble([m for m, _ in trained]).double().eval()
        t1 = time.perf_counter()
        print("[3/4] physics prior: optimum and Hessian of the surrogate", flush=True)
        prior = prior_from_model(
            surrogate,
            model_ring.bounds,
            f_inf=model_ring.loss_background,
            noise=0.04,
            knob_names=model_ring.knob_names,
            provenance={"surrogate_of": f"Spear3Coupling(error_seed={a.model_seed})"},
        )
        print(f"      ({_elapsed(t1)})", flush=True)
        if cache is not None:
            cache.save_prior(key, prior, reports)
    print(f"      condition number {prior.condition_number:.0f}, surrogate optimum "
          f"{prior.f_x0:.3f} mA/min")  # fmt: skip
    return prior


def _with_ensemble(a, prior, ens_hit, rings, cache, ens_key):
    """The prior with the error ensemble's fields, from the cache or the rings' jobs."""
    meta = {"error_seed": a.model_seed}
    if ens_hit is not None:
        print(f"      optima of {a.center_ensemble} ensemble rings from the cache "
              f"({cache.path('ensemble', ens_key)})", flush=True)  # fmt: skip
        return apply_cached_ensemble(prior, ens_hit)
    t0 = time.perf_counter()
    optima = gather_optima([r for part in rings for r in part.result()])
    prior = with_center_ensemble(prior, a.center_ensemble, meta, a.machine_seed, optima=optima)
    print(f"      optima of {len(optima.seeds)} ensemble rings in the prior "
          f"(waited {_elapsed(t0)} for them)", flush=True)  # fmt: skip
    if cache is not None:
        cache.save_ensemble(ens_key, prior)
    return prior
