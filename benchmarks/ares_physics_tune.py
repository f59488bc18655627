"""Tuning script for ``ares-physics`` on the tuning trials (0–49 only; never 50–299).

Runs one method on trials of the shipped trials file with the benchmark's own run loop
(:func:`pigp_torch.machines.ares_ea.benchmark.run_ares_trial`) and prints, per trial, the final
MAE, the steps to 40 / 20 µm and the median CPU time of one step (ask + tell; the process's CPU
time, one thread: the wall time on an idle core, whatever else the machine runs), then the
medians.

    python benchmarks/ares_physics_tune.py --trial-ids 0-9 --steps 150 [--noise 5e-6]
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import statistics
import time

import numpy as np
import torch

from pigp_torch.machines.ares_ea import benchmark as bench
from pigp_torch.machines.ares_ea.simulation import AresSegment, load_trials, parse_trial_ids


def true_optimum(trial, seg) -> float:
    """The smallest MAE (m) of the true machine over the knob box found by least squares on
    observables - target from 64 Sobol starts (each end point scored by its MAE)."""
    from pigp_torch.machines.ares_ea.simulation import knob_bounds
    from pigp_torch.optimizers._least_squares import least_squares_in_box

    b = knob_bounds()

    def obs(X):
        return seg.observe(X, trial.incoming, trial.misalignments)

    Z = torch.quasirandom.SobolEngine(5, scramble=True, seed=0).draw(64, dtype=torch.float64)
    Z = least_squares_in_box(lambda X: obs(X) - trial.target, b, Z, scale=1e-6, max_iter=60)
    with torch.no_grad():
        return float((obs(b[0] + (b[1] - b[0]) * Z) - trial.target).abs().mean(-1).min())


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--trial-ids", default="0-9")
    p.add_argument("--steps", type=int, default=150)
    p.add_argument("--noise", type=float, default=0.0)
    p.add_argument("--method", default="ares-physics")
    p.add_argument("--opt", action="append", default=[], help="KEY=VALUE method option")
    p.add_argument(
        "--true-optimum",
        action="store_true",
        help="print the smallest MAE the true machine reaches (64 least-squares starts) instead",
    )
    a = p.parse_args()
    ids = parse_trial_ids(a.trial_ids)
    if max(ids) >= 50:
        raise SystemExit("tuning uses trials 0-49 only")
    torch.set_num_threads(1)
    trials = load_trials()
    seg = AresSegment()
    if a.true_optimum:
        for i in ids:
            print(f"trial {i:3d}: true optimum MAE {true_optimum(trials[i], seg) * 1e6:.2f} um")
        return
    opts = {}
    for kv in a.opt:
        k, v = kv.split("=", 1)
        opts[k] = ast.literal_eval(v)
    from pigp_torch.methods import METHODS

    spec = METHODS[a.method].with_options(**opts)
    # time each step by wrapping ask/tell of the built optimizer
    times: list[float] = []
    builder = spec.builder
    built: list = []

    def build(ctx, **options):
        opt = builder(ctx, **options)
        ask, tell = opt.ask, opt.tell
        state = {"t": None}

        def timed_ask():
            state["t"] = time.process_time()
            return ask()

        def timed_tell(*args, **kw):
            out = tell(*args, **kw)
            if state["t"] is not None:
                times.append(time.process_time() - state["t"])
            return out

        opt.ask, opt.tell = timed_ask, timed_tell
        built.append(opt)
        return opt

    spec = dataclasses.replace(spec, builder=build)
    rows = []
    all_times = []
    for i in ids:
        times.clear()
        t0 = time.perf_counter()
        df = bench.run_ares_trial(
            trials[i], spec, steps=a.steps, noise=a.noise, seed=i, segment=seg
        )
        wall = time.perf_counter() - t0
        s = bench.score_runs(df).iloc[0]
        med = statistics.median(times) if times else float("nan")
        opt = built[-1]
        alt = ""
        if getattr(opt, "best_from", None) == "model":
            # the other choice of the best setting, scored on the noise-free beam
            from pigp_torch.optimizers.base import AskTellOptimizer

            x_read, _ = AskTellOptimizer.best(opt)
            o = seg.observe(x_read[None], trials[i].incoming, trials[i].misalignments)[0]
            mae_read = float((o - trials[i].target).abs().mean()) * 1e6
            alt = f"  final(best by readings) {mae_read:.3f} um"
        all_times += times
        rows.append((i, s["final_mae"] * 1e6, s["steps_to_40um"], s["steps_to_20um"], med, wall))
        print(
            f"trial {i:3d}: final {s['final_mae'] * 1e6:9.3f} um  "
            f"best {s['best_mae'] * 1e6:9.3f} um"
            f"  to40 {s['steps_to_40um']:4.0f}  to20 {s['steps_to_20um']:4.0f}"
            f"  step CPU median {med:.3f} s  max {max(times):.3f} s  wall {wall:.1f} s{alt}",
            flush=True,
        )
    f = np.array([r[1] for r in rows])
    print(
        f"MEDIAN final {np.median(f):.3f} um  max {f.max():.3f} um  to40 "
        f"{np.median([r[2] for r in rows]):.0f} to20 {np.median([r[3] for r in rows]):.0f}  "
        f"step CPU median {statistics.median(all_times):.3f} s  p90 "
        f"{np.quantile(all_times, 0.9):.3f} s"
    )


if __name__ == "__main__":
    main()
