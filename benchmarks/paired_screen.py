r"""Paired summary of screen runs: each variant against a baseline on the same machines.

Reads the CSVs of :mod:`benchmarks.screen_physics` (several files, e.g. one per machine seed)
and prints, per variant, on the machines where both it and the baseline ran: machines at 95 %
of the gain, median steps to 95 % (a run that never reached counts as one past its budget),
median gain after 20 evaluations, the mean paired differences variant − baseline of the steps
and of the gain after 20 and 40 with their standard errors (:math:`s/\sqrt n` of the per-machine
differences), and the median compute per ask (ms) with its ratio to the baseline's.

A file may also hold per-run scores (``benchmarks/run_scores.py``, no ``step`` column, e.g.
``docs/data/scores_early_asks_2026-12-06.csv``), so that kept runs join new ones; then every
file is scored per run, ``--family`` picks the family's rows, and the compute per ask is the
median over the shared machines of each run's median (ms), its ratio the median of the
per-machine ratios (the two runs of a machine ran in one process, under one load; runs of
different sessions did not).

    python benchmarks/paired_screen.py runs/acq_1*.csv --baseline default
    python benchmarks/paired_screen.py docs/data/scores_early_asks_2026-12-06.csv \
        runs/wide_1??.csv --family wide
"""

from __future__ import annotations

import argparse
import math
import sys

import numpy as np
import pandas as pd
from run_scores import scores_of

from pigp_torch.bench.scoring import run_scores


def paired_table(df: pd.DataFrame, baseline: str = "default") -> pd.DataFrame:
    """One row per method of ``df`` (runs of :func:`~pigp_torch.benchmark.run_benchmark`),
    scored on the machine seeds that the baseline shares with it (module docstring)."""
    ask = df[df["step"] > 0].groupby("method")["ask_time_s"].median() * 1e3
    return paired_scores(run_scores(df), ask, baseline)


def paired_scores(
    scores: pd.DataFrame, ask: pd.Series | None = None, baseline: str = "default"
) -> pd.DataFrame:
    """:func:`paired_table` from per-run ``scores`` (columns ``method``, ``machine_seed``,
    ``reached_95``, ``steps_to_95``, ``gain_20``, ``gain_40``; one run per method and machine)
    and the median compute per ask ``ask`` (ms, indexed by method); ``ask=None``: from the
    scores' per-run ``ask_ms_median``, paired by machine (module docstring)."""
    scores = scores.set_index(["method", "machine_seed"])
    if baseline not in scores.index.get_level_values(0):
        raise ValueError(f"baseline {baseline!r} is not among the runs' methods")
    base = scores.loc[baseline]
    rows = []
    for method in dict.fromkeys(scores.index.get_level_values(0)):
        own = scores.loc[method]
        seeds = own.index.intersection(base.index)
        row = {"method": method, "machines": len(seeds)}
        row["reached_95"] = int(own.loc[seeds, "reached_95"].sum())
        row["steps_median"] = float(own.loc[seeds, "steps_to_95"].median())
        row["gain_20_median"] = float(own.loc[seeds, "gain_20"].median())
        for col, name in (("steps_to_95", "steps"), ("gain_20", "gain_20"), ("gain_40", "gain_40")):
            diff = (own.loc[seeds, col] - base.loc[seeds, col]).to_numpy(dtype=float)
            row[f"d_{name}"] = float(diff.mean())
            sd = float(diff.std(ddof=1)) if len(diff) > 1 else math.nan
            row[f"se_{name}"] = sd / math.sqrt(len(diff)) if len(diff) > 1 else math.nan
        if ask is None:
            own_ms, base_ms = own.loc[seeds, "ask_ms_median"], base.loc[seeds, "ask_ms_median"]
            row["ask_ms_median"] = float(own_ms.median())
            row["ask_ratio"] = float((own_ms / base_ms).median())
        else:
            row["ask_ms_median"] = float(ask[method])
            row["ask_ratio"] = float(ask[method] / ask[baseline])
        rows.append(row)
    return pd.DataFrame(rows).set_index("method")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("csv", nargs="+", help="screen CSV files")
    p.add_argument("--baseline", default="default", help="method name of the baseline")
    p.add_argument("--family", default="project", help="family of per-run score rows")
    args = p.parse_args(argv)
    frames = [pd.read_csv(f) for f in args.csv]
    if all("step" in f.columns for f in frames):
        df = pd.concat(frames, ignore_index=True)
        table = paired_table(df, args.baseline)
    else:  # kept per-run scores among the files: score every file per run
        df = pd.concat([f if "step" not in f.columns else scores_of(f) for f in frames])
        df = df[df["family"] == args.family]
        if df.duplicated(["method", "machine_seed"]).any():
            raise SystemExit("a method ran twice on one machine among the files")
        table = paired_scores(df, None, args.baseline)
    with pd.option_context("display.width", 200):
        print(table.round(3).to_string())
    print(f"(steps in evaluations, gains as fractions of f* - f0, ask in ms; machines: "
          f"{', '.join(str(s) for s in np.unique(df['machine_seed']))})")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
