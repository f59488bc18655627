r"""The "spear3-13" benchmark protocol: runs methods on simulated machines.

* Machine ``s``: ``ring.build(s)`` (a :class:`~pigp_torch.machines.ring.spec.RingSpec`; default the
  SPEAR3 user-mode ring with the 13 knobs of the study, in amps) read through a
  :class:`~pigp_torch.machine.SimulatedMachine` with i.i.d. :math:`\mathcal N(0, 0.04^2)` noise;
  every run starts at all skews zero. Each machine has its own loss-rate map, drawn from its seed
  and never shown to the prior (:func:`machine_loss_map`): background
  :math:`f_\infty (1 + d)` and Touschek scale :math:`g (1 + \epsilon)`, :math:`d \sim
  U[-0.8, 0.3]`, :math:`\epsilon \sim U[-0.3, 0.3]` (vacuum, beam current and fill pattern set
  them; no lattice model knows them). ``machine_maps=False`` gives every machine the model's.
  This is the ``"project"`` family of machines (the default); ``family="wide"`` draws machines
  that vary as much as real rings (tunes, error scale, peak and background per machine;
  :mod:`~.families`). Every run table carries a ``family`` column.
* Model: the physics prior is computed ONCE from a different ring, ``error_seed = model_seed``,
  with :func:`~pigp_torch.prior.prior_from_model` (the model does not know the machine's errors),
  with the same knob set as the machines (``knobs="paper13"``: the 13 windings of the paper;
  ``"all72"``: every skew winding of the ring).
* Score: the noise-free loss rate :math:`f` at every evaluated setting, the start value
  :math:`f_0 = f(0)`, the machine's true optimum :math:`f^*` (multi-start gradient search on the
  differentiable model, :meth:`~..spear3.Spear3Coupling.optimum`), and the gain
  fraction of the best setting evaluated so far,

  .. math:: g_n = \frac{\max_{k \le n} f(x_k) - f_0}{f^* - f_0}.

Seeds. The machine's noise stream is seeded by the machine seed alone (common random numbers:
every method sees the same noise sequence on a machine); the optimizer (and, for ML-II, the
archive) by a stable hash of ``(method name, machine seed)``. Runs are independent, so a process
pool, or a Dask cluster (:mod:`~.distributed`), gives the same table as a
serial loop.
"""

from __future__ import annotations

import dataclasses
import functools
import zlib

import pandas as pd
import torch

from pigp_torch._utils import DTYPE, default_dtype
from pigp_torch.loop import optimize
from pigp_torch.machine import SimulatedMachine
from pigp_torch.machines.ring.bench.archive import machine_archive
from pigp_torch.machines.ring.bench.distributed import check_scheduler, run_jobs
from pigp_torch.machines.ring.bench.families import check_machines
from pigp_torch.machines.ring.bench.machines import (
    _maps_key,
    benchmark_ring,
    machine_optimum,
)
from pigp_torch.machines.ring.bench.scoring import score_run
from pigp_torch.machines.ring.calibration import MAP_SPREAD, machine_loss_map  # noqa: F401
from pigp_torch.machines.ring.ensemble import ensemble_optima, ensemble_seeds
from pigp_torch.machines.ring.ring import RingCoupling
from pigp_torch.machines.ring.spec import RingSpec, as_ring_spec
from pigp_torch.methods import DEFAULT_BUDGETS, MethodSpec, RunContext, resolve_methods
from pigp_torch.prior import PhysicsPrior, prior_from_model

#: Measurement noise of the protocol (mA/min, the paper's SPEAR3 value).
NOISE = 0.04
#: Model rings in the error ensemble that gives the prior's ``center_cov`` and ``peak_shape``
#: (one optimum search each).
ENSEMBLE_SIZE = 40
#: Score columns added to the loop's table, in order.
SCORE_COLUMNS = ("machine_seed", "f_true", "best_f_true", "f0", "f_star", "gain_fraction")
#: Column of every run table that names the machine family (after the score columns).
FAMILY_COLUMN = "family"


def run_seed(method: str, machine_seed: int) -> int:
    """Stable 31-bit seed of one run from the method name and the machine seed."""
    return zlib.crc32(f"{method}|{int(machine_seed)}".encode()) & 0x7FFFFFFF


def model_prior(
    model_seed: int = 0,
    *,
    noise: float = NOISE,
    n_starts: int = 16,
    seed: int = 0,
    knobs=None,
    center_ensemble: int = 0,
    progress: bool = False,
    ring: RingSpec | None = None,
    source: str = "exact",
    n_samples: int = 100_000,
    members: int = 3,
    model: RingCoupling | None = None,
) -> PhysicsPrior:
    """The physics prior from the model ring ``ring.build(model_seed)`` (default SPEAR3;
    ``knobs`` overrides its knob set).

    ``source="exact"`` (default) takes the optimum and Hessian of the ring's own differentiable
    loss rate; ``"surrogate"`` follows the paper's chain: ``n_samples`` simulated readings of
    the model ring (:func:`~pigp_torch.data.sampling.generate_dataset`) train a
    ``members``-network surrogate (:func:`~pigp_torch.surrogate.train_ensemble`), whose
    optimum and autograd Hessian give the prior.

    With ``center_ensemble = n > 0`` it also carries ``center_cov``, the covariance of the
    optimum, and ``peak_shape``, the mean shape of the peak, over ``n`` more model rings with
    error seeds :data:`~pigp_torch.machines.ring.ensemble.ENSEMBLE_SEED0` ... + n - 1
    (:func:`~pigp_torch.machines.ring.ensemble.ensemble_optima`, one optimum search a ring;
    ``progress`` prints one line a ring). :data:`ENSEMBLE_SIZE` is the protocol's choice.

    ``model``: a model ring built elsewhere (e.g. re-tuned, see
    :mod:`~.mismatch`) instead of ``ring.build(model_seed)``; its ensemble
    rings are its own lattice with the ensemble's error seeds.
    """
    if model is None:
        spec = as_ring_spec(ring, knobs=knobs)
        sim = spec.build(int(model_seed))
        provenance = {"model": spec.describe(model_seed), "ring": spec.to_dict()}
    else:
        sim = model
        provenance = {"model": f"{sim.name}, error seed {sim.error_seed} (given)"}
    fields = {}
    if int(center_ensemble) > 0:
        optima = ensemble_optima(ensemble_seeds(int(center_ensemble)), model=sim,
                                 progress=progress)  # fmt: skip
        fields = optima.prior_fields()
        provenance["center_ensemble_seeds"] = optima.seed_range
    if source not in ("exact", "surrogate"):
        raise ValueError(f"source must be 'exact' or 'surrogate', got {source!r}")
    model = sim.loss_rate
    provenance["source"] = source
    if source == "surrogate":
        from pigp_torch.data.sampling import generate_dataset
        from pigp_torch.surrogate import train_ensemble

        if progress:
            print(f"prior: {n_samples} samples of the model ring -> {members}-network surrogate",
                  flush=True)  # fmt: skip
        data = generate_dataset(sim, int(n_samples), seed=0, progress=progress)
        model, reports = train_ensemble(data, n_members=int(members), progress=False)
        provenance["surrogate_val_rel_rmse"] = [float(r["val_rel_rmse"]) for r in reports]
    prior = prior_from_model(
        model,
        sim.bounds,
        f_inf=sim.loss_background,
        noise=noise,
        n_starts=n_starts,
        seed=seed,
        knob_names=sim.knob_names,
        provenance=provenance,
    )
    return dataclasses.replace(prior, **fields) if fields else prior


def run_one(
    spec: MethodSpec,
    machine_seed: int,
    prior: PhysicsPrior | None,
    *,
    budget: int,
    noise: float = NOISE,
    archive_size: int = 300,
    optimum_starts: int = 8,
    knobs=None,
    ring: RingSpec | None = None,
    machine_maps=True,
    family: str = "project",
) -> pd.DataFrame:
    """One run of ``spec`` on machine ``machine_seed``: the scored tidy table (``budget`` rows,
    its last column ``family``).

    The machine has its own loss-rate map (:func:`machine_loss_map`) unless ``machine_maps`` is
    false; the prior always has the model's. ``family``: ``"project"`` (default) or ``"wide"``
    (:func:`~.machines.benchmark_ring`).

    ``optimum_starts=0`` skips the search for :math:`f^*` (``f_star``, ``gain_fraction`` NaN).
    The run executes with torch's default dtype set to float64 (the caller's is restored): BoTorch
    and GPyTorch read it internally and ``import xopt`` changes it process-wide, so without this
    the same run gave different proposals in a process that had imported Xopt.

    ``prior`` may be ``None`` for a method that needs none (``spec.needs_prior`` false, e.g. ML-II),
    so that it can run before the prior is computed.

    Raises:
        ValueError: ``prior`` is for other knobs than ``ring``'s (names must match in order), or
            ``None`` for a method that needs one; a family that cannot build ``ring``'s machines.
    """
    if prior is None and spec.needs_prior:
        raise ValueError(f"method {spec.name} needs a physics prior")
    spec_ring = as_ring_spec(ring, knobs=knobs)
    with default_dtype(DTYPE):  # same numbers whatever the process imported (xopt: float64)
        sim = benchmark_ring(int(machine_seed), spec_ring, machine_maps, family)
        if prior is not None and list(prior.knob_names) != list(sim.knob_names):
            raise ValueError(
                f"the prior is for {prior.dim} knobs {prior.knob_names[:3]}..., the machines have "
                f"{sim.dim} knobs {sim.knob_names[:3]}...: compute the prior "
                "from a model ring with the same knobs"
            )
        machine = SimulatedMachine(sim, noise=noise, seed=int(machine_seed))
        ctx = RunContext(
            machine=machine,
            prior=prior,
            seed=run_seed(spec.name, machine_seed),
            noise=float(noise),
            archive_size=int(archive_size),
            archive=functools.partial(machine_archive, machine),
        )
        optimizer = spec.build(ctx)
        x0 = torch.zeros(sim.dim, dtype=DTYPE)
        table = optimize(machine, optimizer, x0, budget, method=spec.name, restore="none")
        table.insert(1, "machine_seed", int(machine_seed))
        notes = {}  # the optimizer's notices, on the row of the step whose ask made them
        for n in optimizer.notices:
            notes.setdefault(int(n["at_told"]), n["kind"])
        table["notice"] = [notes.get(int(s), "") for s in table["step"]]
        if int(optimum_starts) == 0:  # no f* search: f_star, gain_fraction NaN
            f_star = float("nan")
        else:
            f_star = machine_optimum(machine_seed, optimum_starts, ring=spec_ring,
                                     machine_maps=machine_maps, family=family)  # fmt: skip
        scored = score_run(table, sim, f_star)
        scored[FAMILY_COLUMN] = family
        return scored


def _run_job(args) -> pd.DataFrame:
    spec, seed, prior, kwargs = args
    torch.set_num_threads(1)
    return run_one(spec, seed, prior, **kwargs)


def run_benchmark(
    methods,
    machine_seeds,
    *,
    model_seed: int = 0,
    budgets: dict[str, int] | None = None,
    noise: float = NOISE,
    archive_size: int = 300,
    progress: bool = True,
    n_workers: int = 1,
    prior: PhysicsPrior | None = None,
    optimum_starts: int = 8,
    knobs=None,
    scheduler: str | None = None,
    center_ensemble: int = ENSEMBLE_SIZE,
    ring: RingSpec | None = None,
    machine_maps=True,
    prior_source: str = "exact",
    family: str = "project",
) -> pd.DataFrame:
    r"""Run every method on every machine seed; one tidy row per evaluation.

    Args:
        methods: names from :data:`~pigp_torch.methods.METHODS` and/or
            :class:`~pigp_torch.methods.MethodSpec` objects.
        machine_seeds: error seeds of the machines (distinct integers).
        model_seed: error seed of the model ring the prior is computed from; not a machine seed.
        budgets: evaluations per budget class (start point included), default
            ``{"gp": 100, "direct": 300}``.
        noise: measurement noise standard deviation (mA/min); also the prior's :math:`\sigma_n`.
        archive_size: archive readings for data-informed methods (ML-II).
        progress: tqdm bar over runs.
        n_workers: processes (``>1``: a ``ProcessPoolExecutor``; same numbers as serial); with
            ``scheduler="local"`` the number of Dask worker processes.
        prior: use this prior instead of computing it from ``model_seed`` (from a model, not a
            machine under test, with the same knobs).
        optimum_starts: starts of the search for each machine's :math:`f^*`; ``0``: none,
            ``f_star`` and ``gain_fraction`` NaN (score by ``best_f_true``, e.g. 72 knobs).
        knobs: knob set of the machines and the model ring (``"paper13"``, ``"powered14"``,
            ``"all72"`` or winding names); overrides ``ring``'s.
        scheduler: ``None`` (default): run here, serially or on ``n_workers`` processes; a Dask
            scheduler address (``"tcp://host:8786"``) or ``"local"`` (a ``LocalCluster`` on
            127.0.0.1): one Dask task per run (:mod:`~.distributed`).
        center_ensemble: when the prior is computed here, the number of further model rings
            whose optima give its ``center_cov`` (:func:`model_prior`; 0: none).
        ring: the simulated ring (:class:`~pigp_torch.machines.ring.spec.RingSpec`; default the
            SPEAR3 user-mode ring, 13 knobs in amps).
        machine_maps: ``True`` (default): each machine its own loss-rate map
            (:func:`machine_loss_map`); ``False``: the model's constants; ``(a, b)``: the
            model's background times ``a`` and Touschek scale times ``b`` (:func:`benchmark_ring`).
        prior_source: ``"exact"`` (default) or ``"surrogate"`` (:func:`model_prior`).
        family: ``"project"`` (default) or ``"wide"`` (:func:`benchmark_ring`; same prior).

    Returns:
        DataFrame with columns ``method, machine_seed, step, <knobs>, y, ask_time_s,
        eval_time_s, f_true, best_f_true, f0, f_star, gain_fraction, ..., family``, ordered by
        method and machine seed (as given), step; ``step`` 0 is the start point (skews off).

    Raises:
        ValueError: ``model_seed`` or an ensemble seed among ``machine_seeds``, duplicate
            seeds, unknown methods or budget classes, bad budgets/noise/worker counts, a prior
            for other knobs, an unknown family or one that cannot build ``ring``'s machines.
        ConnectionError: the Dask scheduler cannot be reached (or has no workers) in time.
    """
    specs, ring = resolve_methods(methods), as_ring_spec(ring, knobs=knobs)
    seeds = [int(s) for s in machine_seeds]
    budgets = _check_arguments(
        specs, seeds, model_seed, budgets, noise, n_workers, optimum_starts, scheduler,
        center_ensemble, (family, ring, _maps_key(machine_maps)),
    )  # fmt: skip
    if not any(spec.uses_center_ensemble for spec in specs):
        center_ensemble = 0  # no method reads it: skip the ensemble's optimum searches
    if prior is None:
        prior = _model_prior_for(
            seeds, model_seed, noise, ring, center_ensemble, progress, prior_source
        )
    _check_prior_knobs(prior, ring, seeds[0])
    shared = dict(noise=float(noise), archive_size=int(archive_size), ring=ring, family=family)
    shared.update(optimum_starts=int(optimum_starts), machine_maps=_maps_key(machine_maps))
    return _run_all(specs, seeds, prior, budgets, shared, scheduler, int(n_workers), progress)


def _run_all(specs, seeds, prior, budgets, shared, scheduler, n_workers, progress):
    """One job per (method, machine seed), run by
    :func:`~.distributed.run_jobs`; their tables, concatenated in job order
    with ``method, machine_seed, step`` first."""
    jobs = [
        (spec, seed, prior, {"budget": int(budgets[spec.budget]), **shared})
        for spec in specs
        for seed in seeds
    ]
    labels = [f"{spec.name} seed {seed}" for spec, seed, _, _ in jobs]
    tables = run_jobs(
        _run_job, jobs, scheduler=scheduler, n_workers=n_workers, labels=labels, progress=progress
    )
    df = pd.concat(tables, ignore_index=True)
    first = ["method", "machine_seed", "step"]
    return df[first + [c for c in df.columns if c not in first]]


def _check_arguments(
    specs, seeds, model_seed, budgets, noise, n_workers, optimum_starts, scheduler, center_ensemble,
    machines=("project", None, True)) -> dict[str, int]:  # fmt: skip
    """The checks of :func:`run_benchmark`'s arguments, before anything expensive (an
    unreachable cluster fails before the prior is computed); returns the budgets by class.
    ``machines``: ``(family, ring, machine_maps)``."""
    if not seeds:
        raise ValueError("no machine seeds given")
    if len(set(seeds)) != len(seeds):
        raise ValueError(f"duplicate machine seeds in {seeds}")
    if int(model_seed) in seeds:
        raise ValueError(
            f"model_seed {model_seed} is also a machine seed: the prior must come from a "
            "different ring than the machines it is tested on"
        )
    budgets = {**DEFAULT_BUDGETS, **(budgets or {})}
    for spec in specs:
        if spec.budget not in budgets:
            raise ValueError(f"method {spec.name!r} needs budget class {spec.budget!r}")
        b = budgets[spec.budget]
        if int(b) != b or b < 1:
            raise ValueError(f"budget {spec.budget!r} must be a positive integer, got {b}")
    if not (float(noise) > 0 and float(noise) < float("inf")):
        raise ValueError(f"noise must be positive and finite, got {noise}")
    if int(n_workers) < 1:
        raise ValueError(f"n_workers must be >= 1, got {n_workers}")
    if int(optimum_starts) < 0:
        raise ValueError(f"optimum_starts must be >= 0, got {optimum_starts}")
    if scheduler is not None:
        check_scheduler(scheduler)
    if int(center_ensemble) < 0:
        raise ValueError(f"center_ensemble must be >= 0, got {center_ensemble}")
    check_machines(*machines)
    return budgets


def _model_prior_for(seeds, model_seed, noise, ring, center_ensemble, progress, source):
    """:func:`model_prior` of the benchmark's model ring, whose ensemble rings must not be
    machines under test."""
    shared = set(ensemble_seeds(center_ensemble)) & set(seeds) if center_ensemble else ()
    if shared:
        raise ValueError(
            f"machine seeds {sorted(shared)} are also ensemble seeds of the prior: the "
            "model must not know the machines' errors"
        )
    if progress and center_ensemble:
        print(
            f"prior: model ring {model_seed} + optima of {center_ensemble} ensemble rings",
            flush=True,
        )
    return model_prior(
        model_seed,
        noise=noise,
        ring=ring,
        center_ensemble=center_ensemble,
        progress=progress,
        source=source,
    )


def _check_prior_knobs(prior: PhysicsPrior, ring: RingSpec, seed: int) -> None:
    names = ring.build(seed).knob_names
    if list(prior.knob_names) != names:
        raise ValueError(
            f"the prior is for {prior.dim} knobs, the machines have {len(names)} "
            f"({ring.describe()}): compute the prior from a model ring with the same knobs"
        )
