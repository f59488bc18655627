r"""Merge ``pigp bench ares`` outputs and print the scores, at the full budget and at a shorter one.

``python benchmarks/ares_tables.py DIR [DIR ...] [--budget 50] [--common] [--scores-csv FILE]``
reads ``DIR/steps.csv`` of each run, scores every (method, trial) at its own budget (the
set-back row), and, with ``--budget N``, at a budget of ``N`` readings: the final MAE then is the
best noise-free MAE among the first ``N`` readings (what setting back to the best after ``N``
readings gives on a noise-free screen) and steps to 40 / 20 µm count only the first ``N``.
``--common`` keeps only the trials every method ran.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import pandas as pd

from pigp_torch.machines.ares_ea.benchmark import format_summary, score_runs, summarize_scores


def truncate(table: pd.DataFrame, budget: int) -> pd.DataFrame:
    """The first ``budget`` readings of every run plus a set-back row at the best of them
    (noise-free tables only: the best reading is the best setting)."""
    run = table[table["step"] < budget]
    if (run["mae"] != run["mae_true"]).any():
        raise ValueError("--budget needs noise-free runs")
    best = run.loc[run.groupby(["method", "trial"])["mae_true"].idxmin()].copy()
    best["step"] = budget
    return pd.concat([run, best], ignore_index=True)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("dirs", nargs="+", help="output folders of pigp bench ares")
    p.add_argument("--budget", type=int, default=None, help="also score at this many readings")
    p.add_argument("--common", action="store_true", help="only trials every method ran")
    p.add_argument("--scores-csv", default=None, help="write the per-run scores here")
    args = p.parse_args(argv)
    table = pd.concat([pd.read_csv(Path(d) / "steps.csv") for d in args.dirs], ignore_index=True)
    if args.common:
        per = table.groupby("method")["trial"].unique()
        common = set.intersection(*(set(v) for v in per))
        table = table[table["trial"].isin(common)]
    trials = sorted(table["trial"].unique())
    methods = sorted(table["method"].unique())
    print(f"trials {trials[0]}-{trials[-1]} ({len(trials)}), methods {methods}")
    scores = score_runs(table)
    print("at each run's own budget:")
    print(format_summary(summarize_scores(scores)))
    if args.budget is not None:
        print(f"at a budget of {args.budget} readings:")
        print(format_summary(summarize_scores(score_runs(truncate(table, args.budget)))))
    if args.scores_csv:
        scores.to_csv(args.scores_csv, index=False)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
