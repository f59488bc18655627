r"""Scores of benchmark runs: steps-to-fraction, gain after n evaluations, per-method summary.

All scores use the NOISE-FREE loss rate ``f_true`` of the evaluated settings. A run is the rows of
one ``(method, machine_seed)`` pair; evaluation number :math:`n` = ``step + 1`` (the start point
is evaluation 1).

* Steps-to-:math:`p`: the first :math:`n` with :math:`f(x_n) \ge f_0 + p (f^* - f_0)`. A run that
  never reaches it scores ``budget + 1`` (its number of evaluations + 1), so medians and quartiles
  stay defined and an unreached run ranks behind every reached one; ``reached_95`` says which.
* Steps-to-within: the first :math:`n` with :math:`f(x_n) \ge f^* - \max(0.05 (f^* - f_0),
  \sigma_n)` (``steps_within``; ``budget + 1`` if never).
* Gain after :math:`n`: the ``gain_fraction`` after :math:`n` evaluations (NaN if the run is
  shorter).
* Compute per ask: ``ask_time_s`` of the evaluations after the start point, median and 90th
  percentile per method (s).
* First move of the prior check: the evaluation :math:`n` of a run's first ``prior_rejected``
  notice (a run may move more than once; it counts once, at its first move).
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import torch

from pigp_torch._utils import DTYPE
from pigp_torch.machines.ring.ring import RingCoupling

RUN_KEYS = ["method", "machine_seed"]
_NEEDED = ("method", "machine_seed", "step", "f_true", "f0", "f_star", "gain_fraction")


def _check(df: pd.DataFrame) -> None:
    missing = [c for c in _NEEDED if c not in df.columns]
    if missing:
        raise ValueError(f"benchmark table lacks columns {missing}")
    if df.empty:
        raise ValueError("benchmark table is empty")


def _first(n: np.ndarray, hit: np.ndarray, budget: int) -> float:
    idx = np.flatnonzero(hit)
    return float(n[idx[0]]) if idx.size else float(budget + 1)


def run_scores(
    df: pd.DataFrame, fraction: float = 0.95, at=(20, 40, 100), noise: float = 0.04
) -> pd.DataFrame:
    r"""One row per run: steps-to-``fraction``, whether reached, steps-to-within, gain after
    ``at``, final best.

    Args:
        df: table of :func:`~.run_benchmark` (or with its score columns).
        fraction: :math:`p` of steps-to-:math:`p`, in (0, 1].
        at: evaluation counts for ``gain_<n>`` columns.
        noise: :math:`\sigma_n` of the steps-to-within criterion (mA/min).

    Returns:
        DataFrame with columns ``method, machine_seed, budget, steps_to_<pct>, reached_<pct>,
        steps_within, gain_<n>... , best_f_true`` (``<pct>`` = ``round(100 fraction)``).
    """
    _check(df)
    if not 0.0 < float(fraction) <= 1.0:
        raise ValueError(f"fraction must lie in (0, 1], got {fraction}")
    pct = round(100 * float(fraction))
    rows = []
    for (method, seed), run in df.groupby(RUN_KEYS, sort=False):
        run = run.sort_values("step")
        n = run["step"].to_numpy() + 1
        f0, f_star = float(run["f0"].iloc[0]), float(run["f_star"].iloc[0])
        target = f0 + float(fraction) * (f_star - f0)
        f = run["f_true"].to_numpy()
        budget = int(n.max())
        within = f_star - max(0.05 * (f_star - f0), float(noise))
        row = {
            "method": method,
            "machine_seed": seed,
            "budget": budget,
            f"steps_to_{pct}": _first(n, f >= target, budget),
            f"reached_{pct}": bool((f >= target).any()),
            "steps_within": _first(n, f >= within, budget),
        }
        gain = run["gain_fraction"].to_numpy()
        for k in at:
            idx = np.flatnonzero(n == int(k))
            row[f"gain_{int(k)}"] = float(gain[idx[0]]) if idx.size else float("nan")
        row["best_f_true"] = float(run["f_true"].max())
        rows.append(row)
    return pd.DataFrame(rows)


def first_moves(df: pd.DataFrame) -> pd.Series:
    """Evaluation number of each run's first ``prior_rejected`` notice.

    Args:
        df: evaluation rows (``method``, ``machine_seed``, ``step`` and, when any run wrote
            notices, ``notice``).

    Returns:
        Series indexed by ``(method, machine_seed)``, only the runs that moved (``step + 1`` of
        the first move, an evaluation count).
    """
    # A CSV whose runs wrote no notice reads the column back as float NaN: compare, not fill.
    notice = df["notice"] if "notice" in df.columns else pd.Series("", index=df.index)
    moved = df[notice.eq("prior_rejected")]
    return moved.groupby(["method", "machine_seed"])["step"].min() + 1


def summarize(
    df: pd.DataFrame, fraction: float = 0.95, at=(20, 40, 100), noise: float = 0.04
) -> pd.DataFrame:
    r"""Per method: median and interquartile range over runs of every score.

    For each score ``s`` of :func:`run_scores` (``steps_to_95``, ``steps_within``, ``gain_20``,
    ``gain_40``, ``gain_100``, ``best_f_true``) the columns ``s_median``, ``s_q25``, ``s_q75``
    (linear-interpolated quantiles, NaNs skipped); plus ``n_runs``, ``n_reached_95``, ``budget``
    (max over runs) and, when the table has ``ask_time_s``, ``ask_time_s_median`` and
    ``ask_time_s_p90`` over every ask after the start point.

    Returns:
        DataFrame indexed by method (in order of first appearance).
    """
    scores = run_scores(df, fraction=fraction, at=at, noise=noise)
    pct = round(100 * float(fraction))
    cols = [f"steps_to_{pct}", "steps_within"] + [f"gain_{int(k)}" for k in at] + ["best_f_true"]
    out = []
    for method, g in scores.groupby("method", sort=False):
        row = {
            "method": method,
            "n_runs": len(g),
            f"n_reached_{pct}": int(g[f"reached_{pct}"].sum()),
            "budget": int(g["budget"].max()),
        }
        for c in cols:
            v = g[c].dropna()
            q = v.quantile([0.25, 0.5, 0.75]) if len(v) else pd.Series([np.nan] * 3)
            row[f"{c}_median"], row[f"{c}_q25"], row[f"{c}_q75"] = (
                float(q.iloc[1]),
                float(q.iloc[0]),
                float(q.iloc[2]),
            )
        if "ask_time_s" in df.columns:
            t = df.loc[(df["method"] == method) & (df["step"] > 0), "ask_time_s"].dropna()
            row["ask_time_s_median"] = float(t.median()) if len(t) else float("nan")
            row["ask_time_s_p90"] = float(t.quantile(0.9)) if len(t) else float("nan")
        out.append(row)
    return pd.DataFrame(out).set_index("method")


def score_run(table: pd.DataFrame, sim: RingCoupling, f_star: float) -> pd.DataFrame:
    r"""Add ``f_true``, ``best_f_true``, ``f0``, ``f_star``, ``gain_fraction`` to one run's table.

    ``f_true`` is the noise-free loss rate at the logged knobs (rows in step order),
    ``best_f_true`` its running maximum, ``f0`` the noise-free value with skews off.
    """
    X = torch.as_tensor(table[list(sim.knob_names)].to_numpy(), dtype=DTYPE)
    with torch.no_grad():
        f = sim.loss_rate(X)
        f0 = float(sim.loss_rate(torch.zeros(1, sim.dim, dtype=DTYPE))[0])
    out = table.copy()
    out["f_true"] = f.numpy()
    out["best_f_true"] = out["f_true"].cummax()
    out["f0"] = f0
    out["f_star"] = float(f_star)
    out["gain_fraction"] = (out["best_f_true"] - f0) / (float(f_star) - f0)
    return out
