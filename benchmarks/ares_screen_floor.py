"""How close to its best a run on a noisy ARES screen can end: the screen's resolution floor.

A screen with resolution r reads a beam size as sqrt(sigma^2 + r^2). A model without r that puts
the read numbers exactly on the target sets the true sizes to sqrt(t^2 - r^2) (t > r), so even
its exact optimum has the true MAE (m: the four beam numbers, mean absolute error)

    floor = sum over the two sizes of (t - sqrt(t^2 - r^2)) / 4      (t <= r: t itself)

and a run's final is that floor plus the error of its estimate. This script prints, per trial of
a ``drift_bench.py`` CSV of a family with a screen (``screen-jitter``, ``static``): the floor, the
run's final and best true MAE (µm), final / best and floor / best; and the sd of each beam number
read 200 times at the run's start setting (µm: the scatter a fit sees per number, shot-to-shot
jitter of the incoming beam and the supplies). Reads the CSV only (no run), any trials.

    python benchmarks/ares_screen_floor.py docs/data/ares_screen-jitter_heldout_50-57_2026-12-06.csv
"""

from __future__ import annotations

import argparse
import math
import sys

import pandas as pd
import torch

from pigp_torch.machines import KINDS


def floor_um(target_m, resolution_m: float) -> float:
    """The true MAE (µm) of the beam whose read numbers are ``target_m`` (module docstring)."""
    t = [float(target_m[i]) for i in (1, 3)]  # sigma_x, sigma_y (m)
    r2 = resolution_m**2
    return sum(s - math.sqrt(s * s - r2) if s > resolution_m else s for s in t) / 4 * 1e6


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("csv", help="per-reading CSV of drift_bench.py (method,id,reading,mae_true_um)")
    p.add_argument("--family", default=None, help="the family of the CSV (default: from its name)")
    p.add_argument("--seed", type=int, default=101, help="draw seed of the runs (default 101)")
    p.add_argument("--repeats", type=int, default=200, help="readings for the scatter (200)")
    a = p.parse_args(argv)
    family = a.family or next((f for f in ("screen-jitter", "static") if f"_{f}_" in a.csv), None)
    if family is None:
        print("error: name the family with --family", file=sys.stderr)
        return 2
    d = pd.read_csv(a.csv)
    print(f"family {family}, draw seed {a.seed}; true MAE in um; sd of each number read "
          f"{a.repeats} times at the start setting (mu_x, sigma_x, mu_y, sigma_y; um)")  # fmt: skip
    print("trial  floor  final   best  final/best  floor/best  sd")
    rows = []
    for trial, g in d.groupby("id"):
        m = KINDS["ares-ea"].drift_machine(
            family=family, seed=a.seed, trial=int(trial), objective="mae", noise=0.0
        )
        fl = floor_um(m.target, m.gaps.resolution)
        last = int(g.reading.max())
        final = float(g[g.reading == last].mae_true_um.iloc[0])
        best = float(g[g.reading < last].mae_true_um.min())
        reads = []
        for _ in range(a.repeats):
            m.read()
            reads.append(m.last_observables.clone())
        sd = (torch.stack(reads).std(0) * 1e6).tolist()
        rows.append((fl / best, final / best))
        sds = " / ".join(f"{v:.2f}" for v in sd)
        print(f"{int(trial):5d} {fl:6.2f} {final:6.2f} {best:6.2f} {final / best:10.2f} "
              f"{fl / best:11.2f}  {sds}")  # fmt: skip
    fb = sorted(r[1] for r in rows)
    lb = sorted(r[0] for r in rows)
    mid = len(rows) // 2
    med = lambda v: v[mid] if len(v) % 2 else (v[mid - 1] + v[mid]) / 2  # noqa: E731
    print(f"median final/best {med(fb):.2f}, floor/best {med(lb):.2f}; "
          f"floor/best >= 1.2 on {sum(v >= 1.2 for v in lb)} of {len(lb)}")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
