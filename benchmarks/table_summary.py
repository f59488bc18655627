"""The benchmark table from run CSVs, with each method's steps against the oracle bound.

Joins one or more CSVs of :func:`~pigp_torch.bench.run_benchmark` (e.g. from
``benchmarks/run_table.py``, one per group of methods, all with the same prior) and, when given,
the per-machine oracle bound of ``benchmarks/information_bound.py --csv``. Prints per method:
machines at 95 %, median (IQR) steps to 95 % (an unreached run counts budget + 1), median (IQR)
ratio steps-to-95 / n95, steps within max(5 %, σn), gains after 20 / 40 / 100, compute per ask
(median / p90, ms); then per machine the steps of each method and n95; then the paper's claims.
Runs on machines of another family than ``project`` (the tables' ``family`` column,
:mod:`~pigp_torch.bench.families`) are labelled ``method [family]``, so one table reports
both families; the n95 CSV is matched by family and machine seed.

    python benchmarks/table_summary.py runs/table_main.csv runs/table_xopt.csv --n95 runs/n95.csv
"""

from __future__ import annotations

import argparse

import pandas as pd

from pigp_torch.bench.scoring import run_scores


def iqr(v: pd.Series, fmt: str = "{:.2f}") -> str:
    q = v.quantile([0.25, 0.5, 0.75])
    return f"{fmt.format(q.iloc[1])} ({fmt.format(q.iloc[0])}–{fmt.format(q.iloc[2])})"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("csv", nargs="+", help="run tables (one row per evaluation)")
    p.add_argument("--n95", default=None, help="oracle bound CSV (machine_seed, n95)")
    args = p.parse_args(argv)
    df = pd.concat([pd.read_csv(f) for f in args.csv], ignore_index=True)
    df["family"] = df["family"].fillna("project") if "family" in df else "project"
    other = df["family"] != "project"
    df.loc[other, "method"] = df.loc[other, "method"] + " [" + df.loc[other, "family"] + "]"
    scores = run_scores(df)
    family = df.drop_duplicates(["method", "machine_seed"]).set_index(["method", "machine_seed"])
    keys = pd.MultiIndex.from_frame(scores[["method", "machine_seed"]])
    scores["family"] = family["family"].reindex(keys).to_numpy()
    n95 = None
    if args.n95:
        bound = pd.read_csv(args.n95)
        if "family" not in bound:
            bound["family"] = "project"
        n95 = bound.set_index(["family", "machine_seed"])["n95"]
        keys = pd.MultiIndex.from_frame(scores[["family", "machine_seed"]])
        scores["n95"] = n95.reindex(keys).to_numpy()
        scores["ratio"] = scores["steps_to_95"] / scores["n95"]
    lines = ["| method | budget | reached 95 % | steps to 95 % | ratio to n95 | steps within "
             "max(5 %, σn) | gain after 20 | gain after 40 | gain after 100 | ms per ask |",
             "|---|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for method, g in scores.groupby("method", sort=False):
        t = df.loc[(df["method"] == method) & (df["step"] > 0), "ask_time_s"] * 1000
        ratio = iqr(g["ratio"]) if n95 is not None else "–"
        lines.append(
            f"| `{method}` | {int(g['budget'].max())} | {int(g['reached_95'].sum())}/{len(g)} | "
            f"{iqr(g['steps_to_95'], '{:.1f}')} | {ratio} | {iqr(g['steps_within'], '{:.1f}')} "
            f"| {iqr(g['gain_20'])} | {iqr(g['gain_40'])} | {iqr(g['gain_100'])} | "
            f"{t.median():.0f} / {t.quantile(0.9):.0f} |"
        )
    print("\n".join(lines))
    wide = scores.pivot(index="machine_seed", columns="method", values="steps_to_95")
    if n95 is not None:
        for fam_name, g in n95.groupby(level="family"):
            label = "n95" if fam_name == "project" else f"n95 [{fam_name}]"
            wide[label] = wide.index.map(g.droplevel("family"))
    print("\nsteps to 95 % per machine (budget + 1 = not reached)")
    print(wide.to_string())
    med = scores.groupby("method", sort=False)["steps_to_95"].median()
    gain100 = scores.groupby("method", sort=False)["gain_100"].median()
    print("\nmedian steps to 95 % relative to pigp-physics (censored at budget + 1):")
    if "pigp-physics" in med:
        for m, v in med.items():
            print(f"  {m:>16}: pigp-physics / {m} = {med['pigp-physics'] / v:.2f}")
    print("\nmedian gain after 100 evaluations:", gain100.round(3).to_dict())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
