r"""The ARES-EA closing report: several ``pigp bench ares`` runs -> one table, per-trial scores, a
figure.

``python benchmarks/ares_report.py DIR [DIR ...] --markdown FILE --scores-csv FILE --figure FILE
[--common]``

Each DIR is an output folder of ``pigp bench ares``. Its *condition* is the screen noise and the
wrong-model case of the machine: read from ``DIR/run.json`` (``noise_m``, ``model_error``), or,
for folders written before that file existed, the ``model_error`` column of ``steps.csv``
(``none`` when absent) and the noise seen in the table (noise-free when every reading's MAE equals
the noise-free one, else ``noise ?``). Folders of one condition are merged (chunks of trials,
methods run apart); a (method, trial) run in two folders of one condition is an error.

Outputs:

* ``--markdown``: ONE table, a row per condition and method: runs, readings per run, final MAE
  and best MAE (µm, the noise-free beam; median [IQR] over trials), steps to 40 µm and to 20 µm
  (median [IQR], ``inf``: not reached; steps counted from the start, step 0) and the share of
  trials reaching each (scores of :func:`pigp_torch.machines.ares_ea.benchmark.score_runs`);
* ``--scores-csv``: one row per (condition, method, trial) with those scores (MAE in m);
* ``--figure``: one panel per condition, the median noise-free MAE of the reading at each step
  with its interquartile band, one line per method (log scale, 40 and 20 µm dotted).

``--common`` keeps, per condition, only the trials every method of that condition ran.
``DIR::M1,M2`` takes only methods ``M1``, ``M2`` from that folder (e.g. the published recipes of
a folder whose ``ares-physics`` runs an older version of the method).
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
import pandas as pd

from pigp_torch.machines.ares_ea.benchmark import THRESHOLDS_M, score_runs, summarize_scores

#: Order of the conditions in tables and figures: noise-free before noisy, the published machine
#: before the wrong-model cases.
CASE_ORDER = ("none", "beam-outside", "misalign-3x", "quad-cal-10")


def condition_of(folder: Path, table: pd.DataFrame) -> tuple[str, float, str]:
    """``(model_error, noise_m, label)`` of one run folder (module docstring); ``noise_m`` is
    NaN when only the table says the screen was noisy."""
    run_file = folder / "run.json"
    if run_file.is_file():
        run = json.loads(run_file.read_text())
        case, noise = str(run.get("model_error", "none")), float(run["noise_m"])
    else:
        cases = table["model_error"].unique() if "model_error" in table else ["none"]
        if len(cases) != 1:
            raise ValueError(f"{folder}: several model-error cases {list(cases)} in one table")
        case = str(cases[0])
        noise = 0.0 if (table["mae"] == table["mae_true"]).all() else math.nan
    return case, noise, condition_label(case, noise)


def condition_label(case: str, noise_m: float) -> str:
    """``"noise-free"``, ``"noise 5 µm"``, ``"misalign-3x, noise-free"`` ..."""
    if math.isnan(noise_m):
        screen = "noise ?"
    elif noise_m == 0:
        screen = "noise-free"
    else:
        screen = f"noise {noise_m * 1e6:g} µm"
    return screen if case == "none" else f"{case}, {screen}"


def load_runs(dirs, common: bool = False) -> pd.DataFrame:
    """The per-step tables of ``dirs`` concatenated, with columns ``condition``, ``case`` and
    ``noise_m`` (module docstring)."""
    frames = []
    for d in dirs:
        d, _, only = str(d).partition("::")
        folder = Path(d)
        path = folder / "steps.csv"
        if not path.is_file():
            raise FileNotFoundError(f"no steps.csv in {folder}")
        table = pd.read_csv(path, keep_default_na=False, na_values=[""])
        if only:
            methods = only.split(",")
            missing = sorted(set(methods) - set(table["method"]))
            if missing:
                raise ValueError(f"{folder}: no runs of {missing}")
            table = table[table["method"].isin(methods)]
        case, noise, label = condition_of(folder, table)
        frames.append(table.assign(condition=label, case=case, noise_m=noise, model_error=case))
    runs = pd.concat(frames, ignore_index=True)
    dup = runs[runs["step"] == 0].duplicated(["condition", "method", "trial"])
    if dup.any():
        first = runs[runs["step"] == 0][dup].iloc[0]
        raise ValueError(
            f"{first['method']} trial {first['trial']} ran twice under {first['condition']!r}"
        )
    if common:
        keep = []
        for _, g in runs.groupby("condition", sort=False):
            per = g.groupby("method")["trial"].unique()
            trials = set.intersection(*(set(v) for v in per))
            keep.append(g[g["trial"].isin(trials)])
        runs = pd.concat(keep, ignore_index=True)
    return runs


def _condition_key(runs: pd.DataFrame):
    first = runs.groupby("condition", sort=False)[["case", "noise_m"]].first()
    order = {c: i for i, c in enumerate(CASE_ORDER)}

    def key(label: str):
        case, noise = first.loc[label, "case"], first.loc[label, "noise_m"]
        return (order.get(case, len(order)), math.inf if math.isnan(noise) else noise, label)

    return sorted(first.index, key=key)


def per_trial_scores(runs: pd.DataFrame) -> pd.DataFrame:
    """One row per (condition, method, trial): the condition, ``noise_m``, ``readings`` and the
    scores of :func:`score_runs` (MAE in m, steps ``inf`` when not reached)."""
    out = []
    for label in _condition_key(runs):
        g = runs[runs["condition"] == label]
        s = score_runs(g.drop(columns=["condition", "case", "noise_m"]))
        readings = g.groupby(["method", "trial"])["step"].max().rename("readings").reset_index()
        s = s.merge(readings, on=["method", "trial"])
        s.insert(0, "noise_m", float(g["noise_m"].iloc[0]))
        s.insert(0, "condition", label)
        out.append(s)
    return pd.concat(out, ignore_index=True)


def _iqr(r, col: str, fmt: str) -> str:
    return f"{r[col + '_median']:{fmt}} [{r[col + '_q25']:{fmt}}, {r[col + '_q75']:{fmt}}]"


def markdown_table(scores: pd.DataFrame) -> str:
    """The one table of the report (module docstring) from :func:`per_trial_scores`."""
    head = (
        "| condition | method | runs | readings | final MAE (µm) | best MAE (µm) | "
        "steps to 40 µm | share ≤ 40 µm | steps to 20 µm | share ≤ 20 µm |"
    )
    lines = [head, "|" + "---|" * 10]
    for label, g in scores.groupby("condition", sort=False):
        summary = summarize_scores(g)
        readings = g.groupby("method")["readings"].agg(lambda v: "/".join(map(str, sorted(set(v)))))
        for _, r in summary.iterrows():
            lines.append(
                f"| {label} | `{r['method']}` | {int(r['trials'])} | {readings[r['method']]} | "
                f"{_iqr(r, 'final_mae_um', '.3g')} | {_iqr(r, 'best_mae_um', '.3g')} | "
                f"{_iqr(r, 'steps_to_40um', '.0f')} | {r['share_40um']:.0%} | "
                f"{_iqr(r, 'steps_to_20um', '.0f')} | {r['share_20um']:.0%} |"
            )
    return "\n".join(lines) + "\n"


def mae_quantiles(runs: pd.DataFrame) -> pd.DataFrame:
    """Per (condition, method, step before the set-back): the 25 / 50 / 75 % quantiles of the
    noise-free MAE (µm) over trials: columns ``q25, median, q75, trials``."""
    last = runs.groupby(["condition", "method", "trial"])["step"].transform("max")
    run = runs[runs["step"] < last]
    rows = []
    for (label, method, step), g in run.groupby(["condition", "method", "step"], sort=False):
        q = np.quantile(g["mae_true"].to_numpy() * 1e6, [0.25, 0.5, 0.75])
        rows.append((label, method, int(step), q[0], q[1], q[2], len(g)))
    cols = ["condition", "method", "step", "q25", "median", "q75", "trials"]
    return pd.DataFrame(rows, columns=cols).sort_values(["condition", "method", "step"])


def plot_conditions(runs: pd.DataFrame, path) -> None:
    """The figure (module docstring): one panel per condition."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = _condition_key(runs)
    q = mae_quantiles(runs)
    methods = sorted(runs["method"].unique())
    colors = {m: f"C{i}" for i, m in enumerate(methods)}
    n = len(labels)
    cols = min(n, 3)
    rows = math.ceil(n / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.4 * rows), squeeze=False)
    for ax, label in zip(axes.flat, labels, strict=False):
        for method, g in q[q["condition"] == label].groupby("method", sort=True):
            trials = int(g["trials"].max())
            ax.plot(g["step"], g["median"], color=colors[method], label=f"{method} ({trials})")
            ax.fill_between(g["step"], g["q25"], g["q75"], color=colors[method], alpha=0.2)
        for thr in THRESHOLDS_M:
            ax.axhline(thr * 1e6, color="grey", lw=0.7, ls=":")
        ax.set_yscale("log")
        ax.set_title(label, fontsize=10)
        ax.set_xlabel("step (reading)")
        ax.set_ylabel("MAE to target (µm)")
        ax.legend(fontsize=7)
    for ax in list(axes.flat)[n:]:
        ax.set_visible(False)
    fig.suptitle("ARES-EA: median noise-free MAE at each step, IQR band (runs per method)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument(
        "dirs", nargs="+", help="output folders of pigp bench ares (DIR::M1,M2: only those methods)"
    )
    p.add_argument("--markdown", default=None, help="write the table here (else print it)")
    p.add_argument("--scores-csv", default=None, help="write the per-trial scores here")
    p.add_argument("--figure", default=None, help="write the figure here (PNG)")
    p.add_argument("--common", action="store_true", help="per condition, only common trials")
    args = p.parse_args(argv)
    runs = load_runs(args.dirs, common=args.common)
    scores = per_trial_scores(runs)
    table = markdown_table(scores)
    if args.markdown:
        Path(args.markdown).write_text(table)
        print(f"wrote {args.markdown}")
    else:
        print(table, end="")
    if args.scores_csv:
        scores.to_csv(args.scores_csv, index=False)
        print(f"wrote {args.scores_csv} ({len(scores)} runs)")
    if args.figure:
        plot_conditions(runs, args.figure)
        print(f"wrote {args.figure}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
