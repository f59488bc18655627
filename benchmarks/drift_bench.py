"""Registry methods on drifting and reality-gap machines (docs/drift_families.md).

Each run builds a method of :data:`pigp_torch.methods.METHODS` through ``RunContext`` on a machine
of a family (``KINDS[kind].drift_machine``), drives it by ask/tell for N readings (observables
told to the methods that fit them) and scores the TRUE machine at every reading:

* ``ares``: the true MAE (µm) of (mu_x, sigma_x, mu_y, sigma_y) to the target at each reading;
  per run the median over readings 150-299 (``--window``), the final MAE (after the set-back to
  the method's best), the best MAE, and the *lucky* MAE: the true MAE at the reading whose
  *read* MAE (the screen's, noise included) was the lowest -- what a set-back to the luckiest
  reading gives on a machine that does not drift; per method the median over trials of each.
* ``spear3``: the gain against the moving optimum, (f_t(x_t) - f_t(0)) / (f_t* - f_t(0)); per run
  its mean over evaluations 100-499, per method the mean over seeds (sigma = 0.04 mA/min).

Tuning sets only by default: ARES trials 0-49, SPEAR3 seeds 101 and up; ARES trials 50-149 and
SPEAR3 seeds 1-24 are held out and need ``--held-out`` (report runs, never tuning).

    nice -n 15 python benchmarks/drift_bench.py ares --family drift --trials 0-2 \\
        --methods ares-physics published-nm [--readings 300] [--noise 0] [--csv steps.csv] \\
        [--summary]
    nice -n 15 python benchmarks/drift_bench.py spear3 --family drift --seeds 101-102 \\
        --methods pigp-physics nelder-mead [--readings 500] \\
        [--prior docs/data/prior_spear3_seed0_exact.json | --center-ensemble 40]
    python benchmarks/drift_bench.py ares --from-csv a.csv b.csv   # one --summary table of runs

The compared methods of a drifting machine: ``nelder-mead-restart`` (re-measured best, restart
every 50 readings), ``xopt-tdbo`` (Xopt's time-dependent UCB on the reading clock), ``ml2``,
``published-bo`` (ARES), next to ``nelder-mead``, ``published-nm`` and the physics methods. The
ARES final reading is taken at the optimizer's ``recommend()`` (``drive``'s set-back: e.g. the
re-measured best of ``nelder-mead-restart``, the best reading for optimizers without an estimate).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from concurrent.futures import ProcessPoolExecutor

import numpy as np
import pandas as pd
import torch

from pigp_torch._utils import DTYPE, default_dtype
from pigp_torch.machines import KINDS
from pigp_torch.machines.ares_ea.simulation import parse_trial_ids
from pigp_torch.machines.drift import drive, window_statistic
from pigp_torch.methods import METHODS, RunContext

ARES_HELD_OUT = range(50, 300)
RING_HELD_OUT = range(1, 25)


def ares_run(args) -> dict:
    """One ARES run: ``(trial, method, family, seed, readings, noise, window)`` -> scores and the
    per-reading true MAE (µm)."""
    from pigp_torch.machines.ares_ea.benchmark import check_ares_methods
    from pigp_torch.machines.ares_ea.methods import ares_objective_for

    trial, method, family, seed, readings, noise, window, options = args
    torch.set_num_threads(1)
    (spec,) = check_ares_methods([method])
    spec = spec.with_options(**options) if options else spec
    machine = KINDS["ares-ea"].drift_machine(
        family=family, seed=seed, trial=trial, objective=ares_objective_for(method), noise=noise
    )
    ctx = RunContext(machine=machine, prior=None, seed=seed + trial, archive_size=0,
                     noise=noise if noise > 0 else None, maximize=machine.maximize)  # fmt: skip
    read, observed = machine.read, []

    def read_and_keep():  # the screen's numbers of every reading, noise included
        y = read()
        observed.append(machine.last_observables.clone())
        return y

    machine.read = read_and_keep
    t0 = time.perf_counter()
    with torch.random.fork_rng(devices=[]), default_dtype(DTYPE):
        torch.manual_seed(seed + trial)
        _, true = drive(machine, spec.build(ctx), readings)
    mae = ((true - machine.target).abs().mean(-1) * 1e6).numpy()
    read_mae = ((torch.stack(observed) - machine.target).abs().mean(-1) * 1e6).numpy()
    return {
        "kind": "ares", "method": method, "id": trial, "family": family,
        "window_median": window_statistic(mae[:-1], window, "median"),
        "final": float(mae[-1]), "best": float(mae[:-1].min()), "lucky": lucky(mae, read_mae),
        "series": mae, "read_series": read_mae, "seconds": time.perf_counter() - t0,
    }  # fmt: skip


def lucky(mae, read_mae) -> float:
    """The true MAE (µm) at the reading, before the set-back (the last one), whose read MAE is the
    lowest (the first of equal ones)."""
    return float(mae[:-1][int(np.argmin(read_mae[:-1]))])


def spear3_run(args) -> dict:
    """One SPEAR3 run: ``(seed, method, family, readings, noise, window, prior, options)`` ->
    scores and the per-reading gain against the moving optimum (``options``: the method's)."""
    from pigp_torch.bench.protocol import run_seed
    from pigp_torch.machines.ring.drift import gain_series

    seed, method, family, readings, noise, window, prior, options = args
    torch.set_num_threads(1)
    spec = METHODS[method]
    spec = spec.with_options(**options) if options else spec
    machine = KINDS["spear3"].drift_machine(family=family, seed=seed, noise=noise)
    ctx = RunContext(machine=machine, prior=prior, seed=run_seed(method, seed), noise=noise,
                     archive_size=0)  # fmt: skip
    t0 = time.perf_counter()
    with torch.random.fork_rng(devices=[]), default_dtype(DTYPE):
        torch.manual_seed(run_seed(method, seed))
        X, _ = drive(machine, spec.build(ctx), readings, set_back=False)
    gain, _ = gain_series(machine, X)
    return {
        "kind": "spear3", "method": method, "id": seed, "family": family,
        "window_mean": window_statistic(gain, window, "mean"), "final": float(gain[-1]),
        "series": gain, "seconds": time.perf_counter() - t0,
    }  # fmt: skip


def _ids(text: str, held_out: range, allow: bool, what: str) -> list[int]:
    ids = parse_trial_ids(text)
    bad = [i for i in ids if i in held_out]
    if bad and not allow:
        sys.exit(f"error: {what} {bad} are held out (report only): pass --held-out to run them")
    return ids


def _summary(runs: list[dict]) -> str:
    lines = []
    for method in dict.fromkeys(r["method"] for r in runs):
        rs = [r for r in runs if r["method"] == method]
        if rs[0]["kind"] == "ares":
            med = {k: float(np.median([r[k] for r in rs])) for k in ("window_median", "final",
                                                                     "best")}  # fmt: skip
            lines.append(
                f"{method:<14} {len(rs):>3} trials  median true MAE over window "
                f"{med['window_median']:8.1f} um  final {med['final']:8.1f} um  "
                f"best {med['best']:8.1f} um"
            )
        else:
            lines.append(
                f"{method:<14} {len(rs):>3} seeds  mean gain over window "
                f"{np.mean([r['window_mean'] for r in rs]):.3f}  "
                f"final {np.mean([r['final'] for r in rs]):.3f} (fractions of the moving gain)"
            )
    return "\n".join(lines)


def _median_iqr(values, digits: int) -> str:
    q1, med, q3 = np.percentile(np.asarray(values, dtype=float), [25, 50, 75])
    return f"{med:.{digits}f} ({q1:.{digits}f}–{q3:.{digits}f})"


def summary_table(runs: list[dict]) -> str:
    r"""Markdown table, one row per method: the median over machines (trials / seeds) of each
    run's score, with the interquartile range in brackets (numpy's linear percentiles).

    ARES: the median true MAE over the window, the final and the best true MAE (µm), and the
    lucky MAE (µm) where every run has it (tables written before it have not). SPEAR3: the mean
    gain over the window and the gain at the last reading (fractions of the moving gain).
    """
    ares = runs[0]["kind"] == "ares"
    cols = ("window_median", "final", "best") if ares else ("window_mean", "final")
    head = ("median true MAE over window (µm)", "final MAE (µm)", "best MAE (µm)") if ares else (
        "mean gain over window", "gain at the last reading")  # fmt: skip
    if ares and all("lucky" in r for r in runs):
        cols, head = (*cols, "lucky"), (*head, "lucky MAE (µm)")
    lines = [f"| method | {'trials' if ares else 'seeds'} | " + " | ".join(head) + " |",
             "|---|---|" + "---|" * len(cols)]  # fmt: skip
    for method in dict.fromkeys(r["method"] for r in runs):
        rs = [r for r in runs if r["method"] == method]
        cells = " | ".join(_median_iqr([r[c] for r in rs], 1 if ares else 3) for c in cols)
        lines.append(f"| {method} | {len(rs)} | {cells} |")
    return "\n".join(lines)


def runs_from_csv(paths, window: tuple[int, int]) -> list[dict]:
    """The runs of per-reading tables written by ``--csv`` (ARES: the last row of a run is the
    set-back reading), scored over ``window``."""
    runs = []
    for path in paths:
        df = pd.read_csv(path)
        ares = "mae_true_um" in df.columns
        col = "mae_true_um" if ares else "gain"
        for (method, rid), g in df.groupby(["method", "id"], sort=False):
            v = g.sort_values("reading")[col].to_numpy()
            run = {"kind": "ares" if ares else "spear3", "method": method, "id": int(rid),
                   "series": v, "final": float(v[-1])}  # fmt: skip
            if ares:
                run.update(window_median=window_statistic(v[:-1], window, "median"),
                           best=float(v[:-1].min()))  # fmt: skip
                if "mae_read_um" in df.columns:
                    run["lucky"] = lucky(v, g.sort_values("reading")["mae_read_um"].to_numpy())
            else:
                run["window_mean"] = window_statistic(v, window, "mean")
            runs.append(run)
    return runs


def _jobs(a) -> tuple[list, object]:
    options = json.loads(a.options) if a.options else {}
    if a.kind == "ares":
        trials = _ids(a.trials, ARES_HELD_OUT, a.held_out, "ARES trials")
        window = tuple(a.window or (150, 300))
        return [(t, m, a.family, a.seed, a.readings, a.noise, window, options)
                for m in a.methods for t in trials], ares_run  # fmt: skip
    seeds = _ids(a.seeds, RING_HELD_OUT, a.held_out, "SPEAR3 seeds")
    window = tuple(a.window or (100, 500))
    prior = None
    if a.prior:
        from pigp_torch.prior import PhysicsPrior

        prior = PhysicsPrior.load(a.prior)
        print(f"prior: {a.prior}", flush=True)
    elif any(METHODS[m].needs_prior for m in a.methods):
        from pigp_torch.bench.protocol import model_prior

        print(f"prior: model ring 0, {a.center_ensemble} ensemble rings", flush=True)
        prior = model_prior(0, noise=a.noise, center_ensemble=a.center_ensemble)
    return [(s, m, a.family, a.readings, a.noise, window, prior, options)
            for m in a.methods for s in seeds], spear3_run  # fmt: skip


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("kind", choices=("ares", "spear3"))
    p.add_argument("--family", default="drift")
    p.add_argument("--methods", nargs="+", default=None, help="required unless --from-csv")
    p.add_argument("--trials", default="0-2", help="ARES trial ids (tuning: 0-49)")
    p.add_argument("--seeds", default="101-102", help="SPEAR3 machine seeds (tuning: 101+)")
    p.add_argument("--seed", type=int, default=101, help="ARES draw seed of the family")
    p.add_argument("--readings", type=int, default=None, help="default 300 (ARES), 500 (SPEAR3)")
    p.add_argument("--noise", type=float, default=None,
                   help="screen noise in m (ARES, default 0) / loss-rate noise in mA/min "
                        "(SPEAR3, default 0.04)")  # fmt: skip
    p.add_argument("--window", type=int, nargs=2, default=None, help="readings [lo, hi) scored")
    p.add_argument("--center-ensemble", type=int, default=40)
    p.add_argument("--prior", default=None,
                   help="SPEAR3: a saved prior (e.g. docs/data/prior_spear3_seed0_exact.json, "
                        "model ring 0 + 40 ensemble rings) instead of computing it")  # fmt: skip
    p.add_argument("--workers", type=int, default=1)
    p.add_argument("--held-out", action="store_true")
    p.add_argument(
        "--options",
        default=None,
        help='the methods\' options as JSON, e.g. \'{"fallback": "track"}\' (ARES) or '
        '\'{"forgetting": {"slopes": [0]}}\' (SPEAR3)',
    )
    p.add_argument(
        "--csv",
        default=None,
        help="per-reading table (method, id, reading, true value; ARES: the read MAE too)",
    )
    p.add_argument("--summary", action="store_true",
                   help="markdown table: per method the median over machines (IQR)")  # fmt: skip
    p.add_argument("--from-csv", nargs="+", default=None, metavar="CSV",
                   help="no runs: the --summary table of tables written by --csv")  # fmt: skip
    a = p.parse_args(argv)
    ares = a.kind == "ares"
    if a.from_csv:
        window = tuple(a.window or ((150, 300) if ares else (100, 500)))
        try:
            print(summary_table(runs_from_csv(a.from_csv, window)))
        except (OSError, KeyError, ValueError) as err:
            print(f"error: {err}", file=sys.stderr)
            return 2
        return 0
    if not a.methods:
        print("error: --methods is required (or --from-csv)", file=sys.stderr)
        return 2
    a.readings = a.readings or (300 if ares else 500)
    a.noise = (0.0 if ares else 0.04) if a.noise is None else a.noise
    try:
        if a.family not in KINDS["ares-ea" if ares else "spear3"].drift_families():
            raise ValueError(f"unknown family {a.family!r}")
        jobs, fn = _jobs(a)
    except (KeyError, ValueError, OSError) as err:  # json.JSONDecodeError is a ValueError
        print(f"error: {err}", file=sys.stderr)
        return 2
    runs = []
    pool = ProcessPoolExecutor(a.workers) if a.workers > 1 else None
    for r in pool.map(fn, jobs) if pool else map(fn, jobs):
        unit = "um" if ares else "of the gain"
        score = r["window_median"] if ares else r["window_mean"]
        who = f"{r['method']} {'trial' if ares else 'seed'} {r['id']}"
        best = f", best {r['best']:.3f} {unit}, lucky {r['lucky']:.3f} {unit}" if ares else ""
        print(f"{who}: window {score:.3f} {unit}, final {r['final']:.3f} {unit}{best} "
              f"({r['seconds']:.0f} s)", flush=True)  # fmt: skip
        runs.append(r)
    if pool:
        pool.shutdown()
    print(f"\n{a.kind} family {a.family}, {a.readings} readings:\n{_summary(runs)}")
    if a.summary:
        print(f"\n{summary_table(runs)}")
    if a.csv:
        keys = ("series", "read_series") if ares else ("series",)
        rows = [(r["method"], r["id"], t, *v) for r in runs
                for t, v in enumerate(zip(*(r[k] for k in keys), strict=True))]  # fmt: skip
        cols = ["mae_true_um", "mae_read_um"] if ares else ["gain"]
        pd.DataFrame(rows, columns=["method", "id", "reading", *cols]).to_csv(a.csv, index=False)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
