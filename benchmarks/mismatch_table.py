"""The mismatch suite's table: pigp-physics per case against ML-II and stock Xopt UCB.

Reads the CSVs of ``benchmarks/mismatch.py`` (column ``case``) and the benchmark's run tables
(``benchmarks/run_table.py``: ``ml2`` and ``xopt-ucb`` on the same machines with the machines'
own maps — the baselines of every case whose machines are the benchmark's, since the prior does
not reach them; the loss-map cases carry their own baseline runs). Prints one markdown row per
case: median (IQR) gain after 40 and 100 evaluations of pigp-physics, the better baseline's
medians, whether the suite's two rules hold (gain after 100 ≥ the better baseline's; after 40
not below either by more than 0.05), and when the prior check moved on.

    python benchmarks/mismatch_table.py runs/mismatch_priors.csv runs/mismatch_maps.csv \\
        --control runs/table_main.csv runs/table_xopt.csv

The baselines' runs may also come as kept per-run scores (``--baseline-scores``, the output of
``benchmarks/run_scores.py``, e.g. ``docs/data/scores_all_methods_2026-12-04.csv``): their
``control`` rows of ``ml2`` and ``xopt-ucb`` join the control's, so the table is rebuilt
without rerunning the baselines.
"""

from __future__ import annotations

import argparse

import pandas as pd

from pigp_torch.bench.scoring import first_moves, run_scores

BASELINES = ("ml2", "xopt-ucb")


def _iqr(v: pd.Series) -> str:
    q = v.quantile([0.25, 0.5, 0.75])
    return f"{q.iloc[1]:.2f} ({q.iloc[0]:.2f}–{q.iloc[2]:.2f})"


def _kept_baselines(path: str) -> pd.DataFrame:
    """The ``control`` runs of the baselines in a per-run score CSV of ``run_scores.py``."""
    s = pd.read_csv(path)
    return s[(s["case"] == "control") & s["method"].isin(BASELINES)].drop(columns="case")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("csv", nargs="+", help="mismatch CSVs (with a case column)")
    p.add_argument("--control", nargs="+", required=True, help="benchmark run tables")
    p.add_argument(
        "--baseline-scores", nargs="*", default=[], help="per-run score CSVs of the baselines"
    )
    args = p.parse_args(argv)
    mm = pd.concat([pd.read_csv(f) for f in args.csv], ignore_index=True)
    seeds = sorted(mm["machine_seed"].unique())
    ctl = pd.concat([pd.read_csv(f) for f in args.control], ignore_index=True)
    ctl = ctl[ctl["machine_seed"].isin(seeds)]
    ctl_scores = pd.concat([run_scores(ctl), *map(_kept_baselines, args.baseline_scores)])
    ctl_scores = ctl_scores[ctl_scores["machine_seed"].isin(seeds)]
    rows = [
        "| case | pigp-physics gain 40 | gain 100 | ML-II 40 / 100 | Xopt UCB 40 / 100 | "
        "rule 100 | rule 40 | moved on (runs, median step) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    physics_ctl = ctl_scores[ctl_scores["method"] == "pigp-physics"]
    cases = [("control", physics_ctl, ctl_scores, ctl)]
    for case, g in mm.groupby("case", sort=False):
        s = run_scores(g)
        base = s if set(BASELINES) & set(s["method"]) else ctl_scores
        cases.append((case, s[s["method"] == "pigp-physics"], base, g))
    for case, phys, base, raw in cases:
        meds = {}
        for m in BASELINES:
            b = base[base["method"] == m]
            meds[m] = (b["gain_40"].median(), b["gain_100"].median()) if len(b) else None
        have = [v for v in meds.values() if v is not None]
        g40, g100 = phys["gain_40"].median(), phys["gain_100"].median()
        rule100 = g100 >= max(v[1] for v in have) if have else None
        rule40 = all(g40 >= v[0] - 0.05 for v in have) if have else None
        first = first_moves(raw[raw["method"] == "pigp-physics"])  # one per run that moved
        moved = f"{len(first)}/{len(phys)}"
        if len(first):
            moved += f", {float(first.median()):.0f}"

        def fmt(v):
            return "–" if v is None else f"{v[0]:.2f} / {v[1]:.2f}"

        def ok(v):
            return "–" if v is None else ("yes" if v else "**no**")

        rows.append(
            f"| {case} | {_iqr(phys['gain_40'])} | {_iqr(phys['gain_100'])} | "
            f"{fmt(meds['ml2'])} | {fmt(meds['xopt-ucb'])} | {ok(rule100)} | {ok(rule40)} | "
            f"{moved} |"
        )
    print(f"machines: seeds {[int(s) for s in seeds]}")
    print("\n".join(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
