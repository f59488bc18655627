"""Per-run scores of benchmark CSVs, small enough to keep in the repository.

The run CSVs of ``benchmarks/run_table.py`` and ``benchmarks/mismatch.py`` hold every evaluation
(about 1 MB per 24 runs); this writes one row per run: ``case`` (``control`` for a run table
without one), ``family`` (the machine family, ``project`` for a table without one),
``method``, ``machine_seed``, steps to 95 % (budget + 1 when unreached), whether
reached, steps within max(5 %, σn), the gain fraction after 20 / 40 / 100 evaluations, the
median compute per ask (ms) and the evaluation at which the prior check moved on (empty when it
did not).

    python benchmarks/run_scores.py runs/table_main.csv runs/mismatch_priors.csv \\
        -o docs/data/scores.csv
"""

from __future__ import annotations

import argparse

import pandas as pd

from pigp_torch.bench.scoring import first_moves, run_scores


def scores_of(df: pd.DataFrame) -> pd.DataFrame:
    """One row per ``(case, family, method, machine_seed)`` of an evaluation table."""
    if "case" not in df.columns:
        df = df.assign(case="control")
    if "family" not in df.columns:
        df = df.assign(family="project")
    out = []
    for (case, family), g in df.groupby(["case", "family"], sort=False):
        s = run_scores(g).assign(case=case, family=family)
        keys = pd.MultiIndex.from_frame(s[["method", "machine_seed"]])
        ask = g[g["step"] > 0].groupby(["method", "machine_seed"])["ask_time_s"].median()
        s["ask_ms_median"] = 1e3 * ask.reindex(keys).to_numpy()
        s["prior_rejected_at"] = first_moves(g).reindex(keys).to_numpy()
        out.append(s)
    cols = ["case", "family", "method", "machine_seed", "budget", "steps_to_95", "reached_95",
            "steps_within", "gain_20", "gain_40", "gain_100", "ask_ms_median",
            "prior_rejected_at"]  # fmt: skip
    out = pd.concat(out, ignore_index=True)[cols]
    for c in ("budget", "steps_to_95", "steps_within", "prior_rejected_at"):
        out[c] = out[c].astype("Int64")  # evaluation counts (empty: never)
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("csv", nargs="+", help="run CSVs (one row per evaluation)")
    p.add_argument("-o", "--out", required=True, help="scores CSV (one row per run)")
    args = p.parse_args(argv)
    frames = [scores_of(pd.read_csv(f)) for f in args.csv]
    out = pd.concat(frames, ignore_index=True)
    out.to_csv(args.out, index=False, float_format="%.4f")
    print(f"{len(out)} runs -> {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
