r"""The ARES-EA benchmark as published: trials × methods, the beam at every step, the scores.

One run = one trial (its incoming beam and misalignments, unknown to the method) and one method,
on an :class:`~.machine.AresMachine` reading the method's objective
(:func:`~.methods.ares_objective_for`), run by the loop every machine runs through
(:func:`pigp_torch.loop.optimize`: checked moves and readings). Step 0 measures the start setting
[10, −10, 0, 10, 0]; steps 1 … ``steps − 1`` measure the method's asks; then the knobs are set back
to the method's recommended setting (``recommend()``: the best measured setting by default, where
the evidence puts the optimum for a method with a model of the machine) and the beam is measured
once more (row ``step = steps``).

Per row: the trial, the method, the step, the four beam numbers READ on the screen (m; noisy when
the screen has noise), ``mae`` = their mean absolute error to the target (m), and ``mae_true`` =
the same for the noise-free beam at that setting (equal to ``mae`` without noise). Scores use
``mae_true``:

* final MAE: at the set-back row; best MAE: the smallest over steps ``0 … steps − 1``;
* steps to a threshold (40 µm, 20 µm): the first step whose MAE is at or below it (the start is
  step 0), ``inf`` when none; and the share of trials that reach it.

Each score is summarized per method by the median and the interquartile range over trials.

A wrong-model case (``model_error``, :data:`~.cases.MODEL_ERROR_CASES`)
changes the simulated machine only (its incoming beam, misalignments or quadrupole calibration;
the methods' models keep the published ranges); every row names it in the ``model_error`` column.
The GP methods with the paper's physics prior (``pigp``, ``pigp-fast``) get, per trial, the prior
of the ARES model for the trial's target (:func:`~.prior.ares_prior`;
the unknowns at the centre of their ranges, never the trial's) and read ``"neg-mae"``. Other
methods that need a physics prior, or methods built for another task, cannot run here and are
refused before any run starts.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence

import numpy as np
import pandas as pd
import torch

from pigp_torch.loop import optimize
from pigp_torch.machines.ares_ea.cases import case_machine_parts, check_case
from pigp_torch.machines.ares_ea.machine import AresMachine
from pigp_torch.machines.ares_ea.methods import ares_objective_for
from pigp_torch.machines.ares_ea.prior import (
    ARES_PRIOR_ENSEMBLE,
    ARES_PRIOR_METHODS,
    ARES_PRIOR_OBJECTIVE,
    ares_prior,
    uses_ares_prior,
)
from pigp_torch.machines.ares_ea.simulation import OBSERVABLE_NAMES, AresSegment, AresTrial
from pigp_torch.methods import METHODS, MethodSpec, RunContext, resolve_methods

#: MAE thresholds of the published comparison (m).
THRESHOLDS_M: tuple[float, ...] = (40e-6, 20e-6)
#: Columns of the per-step table.
STEP_COLUMNS: tuple[str, ...] = (
    "trial",
    "method",
    "step",
    *OBSERVABLE_NAMES,
    "mae",
    "mae_true",
    "model_error",
)
#: The recipes run when no method is named (the product's default ARES method first, if any).
DEFAULT_ARES_METHODS: tuple[str, ...] = ("ares-physics", "published-bo", "published-nm")


def default_ares_methods() -> list[str]:
    """The registered methods of :data:`DEFAULT_ARES_METHODS`."""
    return [m for m in DEFAULT_ARES_METHODS if m in METHODS]


def check_ares_methods(methods: Sequence[str | MethodSpec]) -> list[MethodSpec]:
    """The specs of ``methods`` if each can run on the ARES machine: built for it or for any
    machine, and needing either no physics prior or the ARES model's
    (:data:`~.prior.ARES_PRIOR_METHODS`).

    Raises:
        ValueError: an unknown method, or one that cannot run here (one line).
    """
    specs = resolve_methods(list(methods))
    for spec in specs:
        if spec.needs_prior and not uses_ares_prior(spec):
            raise ValueError(
                f"method {spec.name!r} needs a ring's physics prior, which the ARES task has "
                f"not; on ARES use {', '.join(ARES_PRIOR_METHODS)} (prior from the ARES model), "
                "ares-physics, ml2, published-bo, published-nm, nelder-mead"
            )
        if spec.machine not in (None, "ares-ea"):
            raise ValueError(f"method {spec.name!r} is built for {spec.machine!r}, not ares-ea")
    return specs


def _trial_machine(trial, spec: MethodSpec, noise: float, seed: int, segment, model_error: str):
    """``(machine, ctx)`` of :func:`run_ares_trial`: the trial's machine (changed by
    ``model_error``) reading the method's objective, and the method's :class:`RunContext` (the
    model's prior for the methods that need one)."""
    if check_case(model_error) != "none":
        trial_m, segment = case_machine_parts(trial, model_error)
    else:
        trial_m = trial
    with_prior = uses_ares_prior(spec)
    objective = ARES_PRIOR_OBJECTIVE if with_prior else ares_objective_for(spec.name)
    machine = AresMachine(trial_m, objective=objective, noise=noise, seed=seed, segment=segment)
    prior = None
    if with_prior:
        n_ens = ARES_PRIOR_ENSEMBLE if spec.uses_center_ensemble else 0
        prior = ares_prior(trial.target, noise, n_ensemble=n_ens)
    ctx = RunContext(
        machine=machine,
        prior=prior,
        seed=seed,
        noise=float(noise) if noise > 0 else None,
        archive_size=0,
        maximize=machine.maximize,
    )
    return machine, ctx


def run_ares_trial(
    trial: AresTrial,
    method: str | MethodSpec,
    *,
    steps: int = 150,
    noise: float = 0.0,
    seed: int = 0,
    segment: AresSegment | None = None,
    model_error: str = "none",
) -> pd.DataFrame:
    r"""One trial tuned by one method: ``steps + 1`` rows of :data:`STEP_COLUMNS` (module
    docstring).

    Args:
        trial: the trial.
        method: a registered name or a :class:`MethodSpec`.
        steps: measurements of the run, the start included (default 150).
        noise: screen noise standard deviation (m) on each of the four numbers (default 0).
            The method's ``RunContext.noise`` is this number in m (``None`` when 0): methods that
            fit the four numbers (``ares-physics``) use it as their noise; the GP methods on the
            scalar objective (``ml2``, ``published-bo``) learn their noise from the readings; the
            prior methods (``pigp``) take the prior's noise
            (:func:`~.prior.prior_noise`).
        seed: seed of the method, of the screen noise and of torch's global generator during
            the run (restored afterwards), so that a run repeats to the bit.
        segment: a shared :class:`AresSegment` (default: a new one) for ``model_error="none"``.
        model_error: the wrong-model case of the machine
            (:data:`~.cases.MODEL_ERROR_CASES`, default ``"none"``).

    Raises:
        ValueError: ``steps < 1``, an unknown case, or a method that cannot run on ARES.
    """
    if int(steps) < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    (spec,) = check_ares_methods([method])
    machine, ctx = _trial_machine(trial, spec, noise, seed, segment, model_error)
    rows = []

    def record(step: int) -> None:
        obs = machine.last_observables
        true = machine.true_observables(machine.get())
        rows.append(
            [
                trial.index,
                spec.name,
                step,
                *obs.tolist(),
                float(machine.mae(obs)),
                float(machine.mae(true)),
                model_error,
            ]
        )

    # Libraries that draw from torch's global generator (BoTorch's hyperparameter fits and
    # acquisition starts) draw the same numbers for the same seed, so a run repeats to the bit;
    # the caller's generator state is restored afterwards. The steps are the one loop's
    # (pigp_torch.loop.optimize), with the readings as they come (no stated noise: no re-reads),
    # the knobs left where the last step put them; then set back to the method's recommended
    # setting (recommend(): the best reading, or where a model puts the optimum).
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        opt = spec.build(ctx)
        optimize(machine, opt, None, int(steps), method=spec.name, restore="none",
                 handle_signals=False, callback=lambda row: record(int(row["step"])))  # fmt: skip
        x_final = opt.recommend()
    machine.set(x_final)
    machine.read()
    record(int(steps))
    return pd.DataFrame(rows, columns=list(STEP_COLUMNS))


def _job(args) -> pd.DataFrame:
    trial, method, steps, noise, seed, model_error = args
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    df = run_ares_trial(trial, method, steps=steps, noise=noise, seed=seed, model_error=model_error)
    df.attrs["seconds"] = time.perf_counter() - t0
    return df


def run_ares_benchmark(
    trials: Sequence[AresTrial],
    methods: Sequence[str],
    *,
    steps: int = 150,
    noise: float = 0.0,
    seed: int = 0,
    workers: int = 1,
    progress: Callable[[str], None] | None = None,
    model_error: str = "none",
) -> pd.DataFrame:
    r"""Every trial × method (:func:`run_ares_trial`, the method's seed = ``seed`` + the trial's
    number); the concatenated per-step table, sorted by method, trial and step.

    Args:
        workers: processes (1: in this process).
        progress: called with one line per finished run.
        model_error: the machine's wrong-model case (:func:`run_ares_trial`).

    Raises:
        ValueError: a method that cannot run on ARES or an unknown case, before any run.
    """
    names = [s.name for s in check_ares_methods(list(methods))]
    check_case(model_error)
    jobs = [
        (t, m, int(steps), float(noise), int(seed) + t.index, model_error)
        for t in trials
        for m in names
    ]
    frames = []

    def report(df: pd.DataFrame) -> None:
        frames.append(df)
        if progress is not None:
            last = df.iloc[-1]
            hit = df.loc[df["step"] < steps, "mae_true"]
            progress(
                f"trial {int(last['trial'])} {last['method']}: final MAE "
                f"{last['mae_true'] * 1e6:.1f} um, best {hit.min() * 1e6:.1f} um "
                f"({df.attrs.get('seconds', float('nan')):.1f} s) "
                f"[{len(frames)}/{len(jobs)}]"
            )

    if int(workers) <= 1:
        for job in jobs:
            report(_job(job))
    else:
        from concurrent.futures import ProcessPoolExecutor, as_completed

        with ProcessPoolExecutor(max_workers=int(workers)) as pool:
            futures = [pool.submit(_job, job) for job in jobs]
            for fut in as_completed(futures):
                report(fut.result())
    table = pd.concat(frames, ignore_index=True)
    return table.sort_values(["method", "trial", "step"], kind="stable").reset_index(drop=True)


def _steps_to(mae: np.ndarray, threshold: float) -> float:
    hit = np.nonzero(mae <= threshold)[0]
    return float(hit[0]) if hit.size else math.inf


def score_runs(table: pd.DataFrame) -> pd.DataFrame:
    r"""Per (method, trial): ``model_error`` (the case; ``"none"`` for rows written before the
    column existed, empty in a merged table), ``final_mae``, ``best_mae`` (m),
    ``steps_to_40um``, ``steps_to_20um`` (``inf``: never) from a per-step table in which each
    run has one case (module docstring).

    Raises:
        ValueError: a (method, trial) with rows of several cases.
    """
    out = []
    for (method, trial), g in table.groupby(["method", "trial"], sort=True):
        g = g.sort_values("step")
        steps = int(g["step"].max())
        run = g.loc[g["step"] < steps, "mae_true"].to_numpy()
        cases = g["model_error"].fillna("none").unique() if "model_error" in g else ["none"]
        if len(cases) != 1:
            raise ValueError(f"{method} trial {trial}: rows of several model-error cases {cases}")
        row = {
            "method": method,
            "trial": int(trial),
            "model_error": str(cases[0]),
            "final_mae": float(g.loc[g["step"] == steps, "mae_true"].iloc[0]),
            "best_mae": float(run.min()),
        }
        for thr in THRESHOLDS_M:
            row[f"steps_to_{round(thr * 1e6)}um"] = _steps_to(run, thr)
        out.append(row)
    return pd.DataFrame(out)


def summarize_scores(scores: pd.DataFrame) -> pd.DataFrame:
    r"""Per method: median, 25 % and 75 % quantiles of final and best MAE (µm) and of the steps
    to 40 / 20 µm (``inf`` counts as not reached), and the share of trials reaching each; the
    ``model_error`` case(s) of its runs (joined by ``+`` if several)."""
    rows = []
    for method, g in scores.groupby("method", sort=False):
        cases = sorted(g["model_error"].unique()) if "model_error" in g else ["none"]
        row = {"method": method, "trials": len(g), "model_error": "+".join(cases)}
        for col in ("final_mae", "best_mae"):
            q = np.quantile(g[col].to_numpy() * 1e6, [0.25, 0.5, 0.75])
            row.update({f"{col}_um_q25": q[0], f"{col}_um_median": q[1], f"{col}_um_q75": q[2]})
        for thr in THRESHOLDS_M:
            col = f"steps_to_{round(thr * 1e6)}um"
            v = g[col].to_numpy()
            q = np.quantile(v, [0.25, 0.5, 0.75], method="lower")
            row.update({f"{col}_q25": q[0], f"{col}_median": q[1], f"{col}_q75": q[2]})
            row[f"share_{round(thr * 1e6)}um"] = float(np.isfinite(v).mean())
        rows.append(row)
    return pd.DataFrame(rows)


def format_summary(summary: pd.DataFrame) -> str:
    """The summary as a text table (MAE in µm, steps as median [IQR])."""
    lines = [
        f"{'method':<16} {'trials':>6}  {'final MAE um':>24}  {'best MAE um':>24}  "
        f"{'steps to 40 um':>18} {'share':>5}  {'steps to 20 um':>18} {'share':>5}"
    ]

    def iqr(r, c, fmt, width):
        text = f"{r[c + '_median']:{fmt}} [{r[c + '_q25']:{fmt}}, {r[c + '_q75']:{fmt}}]"
        return text.rjust(width)

    for _, r in summary.iterrows():
        lines.append(
            f"{r['method']:<16} {int(r['trials']):>6}  {iqr(r, 'final_mae_um', '.1f', 24)}  "
            f"{iqr(r, 'best_mae_um', '.1f', 24)}  {iqr(r, 'steps_to_40um', '.0f', 18)} "
            f"{r['share_40um']:>5.0%}  {iqr(r, 'steps_to_20um', '.0f', 18)} "
            f"{r['share_20um']:>5.0%}"
        )
    return "\n".join(lines)


def plot_mae_vs_step(table: pd.DataFrame, path) -> None:
    """Median MAE (µm, noise-free) against step with the interquartile band, one line per method;
    left: the MAE at each step, right: the best so far."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    run = table[table["step"] < table.groupby(["method", "trial"])["step"].transform("max")]
    fig, axes = plt.subplots(1, 2, figsize=(10, 4), sharey=True)
    for method, g in run.groupby("method", sort=False):
        wide = g.pivot(index="step", columns="trial", values="mae_true") * 1e6
        for ax, data in ((axes[0], wide), (axes[1], wide.cummin())):
            q = np.nanquantile(data.to_numpy(), [0.25, 0.5, 0.75], axis=1)
            (line,) = ax.plot(data.index, q[1], label=f"{method} ({wide.shape[1]} trials)")
            ax.fill_between(data.index, q[0], q[2], color=line.get_color(), alpha=0.2)
    for ax, title in zip(axes, ("MAE at each step", "best MAE so far"), strict=True):
        ax.set_yscale("log")
        ax.set_xlabel("step")
        ax.set_title(title)
        for thr in THRESHOLDS_M:
            ax.axhline(thr * 1e6, color="grey", lw=0.7, ls=":")
    axes[0].set_ylabel("MAE to target (µm), median and IQR")
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
