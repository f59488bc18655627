r"""Figures of a benchmark table in the style of the paper's Fig. 2b and 2c (matplotlib, Agg).

Both plot, against the evaluation number ``step + 1``, the best-so-far NOISE-FREE loss rate
(``best_f_true``) or the ``gain_fraction``: one thin line per run and one thick line (the mean over
the method's runs, over the evaluations all its runs reached) per method, one colour per method.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import pandas as pd

from pigp_torch.machines.ring.bench.scoring import RUN_KEYS

Y_LABELS = {
    "best_f_true": "best noise-free loss rate so far (mA/min)",
    "gain_fraction": r"gain fraction $(f_{best} - f_0)/(f^* - f_0)$",
}


def _draw(ax, df: pd.DataFrame, y: str, labels: dict[str, str] | None = None) -> None:
    if y not in Y_LABELS:
        raise ValueError(f"y must be one of {sorted(Y_LABELS)}, got {y!r}")
    missing = [c for c in (*RUN_KEYS, "step", y) if c not in df.columns]
    if missing:
        raise ValueError(f"benchmark table lacks columns {missing}")
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for i, (method, g) in enumerate(df.groupby("method", sort=False)):
        colour = colours[i % len(colours)]
        for _, run in g.groupby("machine_seed", sort=False):
            run = run.sort_values("step")
            ax.plot(run["step"] + 1, run[y], color=colour, lw=0.6, alpha=0.35)
        n_common = int(g.groupby("machine_seed")["step"].max().min()) + 1
        mean = g[g["step"] < n_common].groupby("step")[y].mean()
        label = (labels or {}).get(method, method)
        ax.plot(mean.index + 1, mean.to_numpy(), color=colour, lw=2.5, label=label)
    if y == "best_f_true" and "f_star" in df.columns:
        optima = df["f_star"].unique()
        for k, f_star in enumerate(optima):  # one legend entry: the value, or "each machine's"
            label = (f"true optimum {f_star:.4g} mA/min" if len(optima) == 1
                     else "true optimum of each machine") if k == 0 else None  # fmt: skip
            ax.axhline(f_star, color="0.5", lw=0.8 if len(optima) == 1 else 0.5, ls=":",
                       label=label)  # fmt: skip
    ax.set_xlabel("evaluation")
    ax.set_ylabel(Y_LABELS[y])
    ax.legend(loc="upper left", fontsize="small")


def plot_runs(df: pd.DataFrame, path, *, y: str = "best_f_true", title: str | None = None):
    """Fig. 2b style: every run thin, the mean per method thick; saved to ``path``.

    Args:
        df: table of :func:`~.run_benchmark`.
        path: output file (format from the suffix, e.g. ``.png``/``.pdf``).
        y: ``"best_f_true"`` (default) or ``"gain_fraction"``.
        title: optional axes title.

    Returns:
        The matplotlib ``Figure`` (closed: use it for inspection, not for display). Its axes hold
        one line per run, then one per method (the mean), method by method, plus one horizontal
        ``f*`` line per distinct optimum when ``y="best_f_true"``.
    """
    fig, ax = plt.subplots(figsize=(6.4, 4.4))
    _draw(ax, df, y)
    if title:
        ax.set_title(title)
    fig.tight_layout()
    fig.savefig(Path(path), dpi=150)
    plt.close(fig)
    return fig


def plot_prior_mean(
    df: pd.DataFrame,
    path,
    *,
    methods=("pigp", "pigp-zero-mean"),
    y: str = "best_f_true",
):
    r"""Fig. 2c style: PI-GP with prior mean :math:`f_\infty` vs zero prior mean.

    Args:
        df: table containing the runs of both ``methods``.
        path: output file.
        methods: the two method names to compare (default ``("pigp", "pigp-zero-mean")``).
        y: ``"best_f_true"`` or ``"gain_fraction"``.

    Returns:
        The (closed) ``Figure``, as :func:`plot_runs`.

    Raises:
        ValueError: a method of ``methods`` has no runs in ``df``.
    """
    absent = [m for m in methods if m not in set(df["method"])]
    if absent:
        raise ValueError(f"no runs of {absent} in the table")
    sub = df[df["method"].isin(list(methods))]
    labels = {methods[0]: r"prior mean $f_\infty$", methods[1]: "prior mean 0"}
    fig, ax = plt.subplots(figsize=(6.4, 4.4))
    _draw(ax, sub, y, labels=labels if len(methods) == 2 else None)
    ax.set_title("PI-GP: effect of the prior mean")
    fig.tight_layout()
    fig.savefig(Path(path), dpi=150)
    plt.close(fig)
    return fig
