r"""Where the runs of ``pigp-physics`` lose evaluations: the fitted centre, the trust box, stalls.

Reruns the protocol of ``benchmarks/screen_physics.py`` (same variant syntax; the variant's name
sets the run's seed, so each run is the screen's run to the bit) on tuning machines, records
after every ask the fitted centre :math:`\hat x_n` (the form fitted to the first :math:`n`
readings) and the search box, and scores each run against the machine's true, noise-free loss
rate :math:`f` (gain fractions :math:`g(x) = (f(x) - f_0)/(f^* - f_0)`):

* ``steps``: evaluations to a reading at :math:`g \ge 0.95` (budget + 1 when never);
* ``centre_at``: the fewest readings :math:`n` after which the fitted centre is good,
  :math:`g(\hat x_n) \ge 0.95` (:math:`\hat x_n` clipped to the knob bounds); budget + 1 when
  never. The ask right after it could read at 95 %, so ``steps - centre_at - 1`` evaluations
  (``after``) are spent between a good fitted centre and a reading that uses it;
* ``clipped``: asks up to the reading at 95 % with a knob on the search box's edge (within
  1e-9 of the half-range) while the fitted centre lay outside that box: the trust box or the travel
  limit held the ask back;
* ``info``: asks up to the reading at 95 % that maximized a centre information, not the UCB;
* ``stall``: the most consecutive evaluations before ``steps`` in which the best true gain
  rose by less than 0.01;
* ``centre_gain_N`` (N = 10, 20, 30, 40): :math:`g(\hat x_N)`, the gain fraction at the
  fitted centre after N readings (a fraction; empty past the budget).

Prints one row per run, then per variant the medians and the means with standard errors over
the machines. Units: evaluations (counts).

    python benchmarks/early_losses.py --prior docs/data/prior_spear3_seed0_surrogate.json \\
        --seeds 101-112 --budget 50 -o runs/early_losses.csv default 'exp:{"schedule": "uue"}'
    python benchmarks/early_losses.py --from runs/loss_1*.csv    # the summary of kept runs
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import sys

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np
import pandas as pd
import torch
from screen_physics import base_spec, parse_variant

from pigp_torch.bench.families import FAMILIES
from pigp_torch.bench.machines import benchmark_ring, machine_optimum
from pigp_torch.bench.protocol import run_one
from pigp_torch.machines.ring.spec import as_ring_spec
from pigp_torch.prior import PhysicsPrior

#: Gain fraction of a good fitted centre and of a reached run.
GOOD = 0.95
#: Rise of the best true gain that ends a stall.
STALL_RISE = 0.01


def recording(spec, log: list[dict]):
    """``spec`` whose optimizers append, after every ask, the ask ``x``, the fitted centre,
    the search box and whether it was an information ask to ``log`` (one dict per ask)."""

    def builder(ctx, **options):
        optimizer = spec.builder(ctx, **options)
        ask = optimizer.ask

        def recorded_ask():
            x = ask()
            info = optimizer.last_info
            log.append({"x": x.detach().clone(), "centre": info["fitted_center"].detach().clone(),
                        "lower": info["trust_lower"], "upper": info["trust_upper"],
                        "inform": bool(info.get("inform", False))})  # fmt: skip
            return x

        optimizer.ask = recorded_ask
        return optimizer

    return dataclasses.replace(spec, builder=builder)


def run_losses(spec, seed: int, prior, budget: int, family: str) -> dict:
    """One instrumented run of ``spec`` on machine ``seed``: the counts of the module
    docstring (:func:`count_losses`)."""
    log: list[dict] = []
    table = run_one(recording(spec, log), seed, prior, budget=budget, family=family)
    sim = benchmark_ring(seed, as_ring_spec(None), True, family)
    f0 = float(table["f0"].iloc[0])
    f_star = machine_optimum(seed, 8, machine_maps=True, family=family)
    centres = torch.stack([r["centre"] for r in log])
    centres = torch.minimum(torch.maximum(centres, sim.bounds[0]), sim.bounds[1])
    with torch.no_grad():
        g_centre = ((sim.loss_rate(centres) - f0) / (f_star - f0)).numpy()
    gain = table.sort_values("step")["gain_fraction"].to_numpy()
    half = (sim.bounds[1] - sim.bounds[0]) / 2
    counts = count_losses(gain, g_centre, log, half, budget)
    return {"method": spec.name, "machine_seed": seed, **counts}


def count_losses(gain, g_centre, log: list[dict], half: torch.Tensor, budget: int) -> dict:
    """The counts of the module docstring from one run: ``gain`` (``budget``) the true gain
    fraction of each evaluation in order, ``g_centre`` (``budget - 1``) that of the fitted
    centre at each ask (``g_centre[k]`` after ``k + 1`` readings), ``log`` the asks of
    :func:`recording`, ``half`` (``d``) the knobs' half-ranges."""
    hit = np.flatnonzero(np.asarray(gain) >= GOOD)
    steps = int(hit[0]) + 1 if hit.size else budget + 1
    good = np.flatnonzero(np.asarray(g_centre) >= GOOD)
    centre_at = int(good[0]) + 1 if good.size else budget + 1
    clipped = info = 0
    for r in log[: max(min(steps, budget) - 1, 0)]:  # the asks up to the reading at 95 %
        edge = ((r["x"] - r["lower"]).abs() < 1e-9 * half) | (
            (r["upper"] - r["x"]).abs() < 1e-9 * half
        )
        outside = bool(((r["centre"] < r["lower"]) | (r["centre"] > r["upper"])).any())
        clipped += int(bool(edge.any()) and outside)
        info += int(r["inform"])
    stall = run = 0
    best = gain[0]
    for g in gain[1 : min(steps, budget)]:
        run = 0 if g >= best + STALL_RISE else run + 1
        best = max(best, g)
        stall = max(stall, run)
    after = steps - centre_at - 1 if centre_at < steps else math.nan
    at = {f"centre_gain_{n}": float(g_centre[n - 1]) if n <= len(g_centre) else math.nan
          for n in (10, 20, 30, 40)}  # fmt: skip
    return {"steps": steps, "centre_at": centre_at, "after": after, "clipped": clipped,
            "info": info, "stall": stall, **at}  # fmt: skip


def summary(df: pd.DataFrame) -> pd.DataFrame:
    """Per method: median and mean ± standard error over the machines of every count."""
    cols = ["steps", "centre_at", "after", "clipped", "info", "stall"]
    cols += [c for c in df.columns if c.startswith("centre_gain_")]
    out = {}
    for method, g in df.groupby("method", sort=False):
        row = {"machines": len(g)}
        for c in cols:
            v = g[c].dropna().to_numpy(dtype=float)
            se = v.std(ddof=1) / math.sqrt(len(v)) if len(v) > 1 else math.nan
            row[f"{c}_median"] = float(np.median(v)) if len(v) else math.nan
            digits = 3 if c.startswith("centre_gain") else 1
            row[f"{c}_mean"] = f"{v.mean():.{digits}f} ± {se:.{digits}f}" if len(v) else ""
        out[method] = row
    return pd.DataFrame(out).T


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("variants", nargs="*", help="as benchmarks/screen_physics.py")
    p.add_argument("--seeds", default="101-112", help="tuning machine seeds a-b (>= 101)")
    p.add_argument("--budget", type=int, default=50)
    p.add_argument("--prior", help="prior JSON file (needed to run)")
    p.add_argument("--from", dest="kept", nargs="+", help="summarize these per-run CSVs")
    p.add_argument("--family", choices=FAMILIES, default="project")
    p.add_argument("-o", "--out", help="CSV of the per-run counts")
    args = p.parse_args(argv)
    if args.kept:
        print_summary(pd.concat([pd.read_csv(f) for f in args.kept], ignore_index=True))
        return 0
    if not (args.prior and args.variants):
        raise SystemExit("give --prior and the variants to run (or --from CSV files)")
    a, b = (int(v) for v in args.seeds.split("-"))
    if a <= 24:
        raise SystemExit("tune on seeds outside the benchmark's 1-24")
    prior = PhysicsPrior.load(args.prior)
    specs = [base_spec(n).with_options(name=n, **o) for n, o in map(parse_variant, args.variants)]
    rows = []
    for seed in range(a, b + 1):
        for spec in specs:
            rows.append(run_losses(spec, seed, prior, args.budget, args.family))
            print(rows[-1], flush=True)
    df = pd.DataFrame(rows)
    if args.out:
        df.to_csv(args.out, index=False)
    print_summary(df)
    return 0


def print_summary(df: pd.DataFrame) -> None:
    """Print :func:`summary` of the per-run rows ``df``."""
    with pd.option_context("display.width", 250, "display.max_columns", 40):
        print(summary(df).T.to_string())
    print("(counts in evaluations, centre gains as fractions of f* - f0; medians and means ± SE "
          f"over the machines {sorted(set(df['machine_seed']))})")  # fmt: skip


if __name__ == "__main__":
    sys.exit(main())
