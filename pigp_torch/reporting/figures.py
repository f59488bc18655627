"""The figures of :mod:`pigp_torch.reporting.report`: one run (:func:`draw_run`,
:func:`plot_run`) and a ``pigp compare`` folder (:func:`plot_compare`); matplotlib, Agg backend.
"""

from __future__ import annotations

from pathlib import Path

import torch


def _knob_style(i: int, k: int) -> dict:
    """Colour (and, beyond 20 knobs, line style) of knob ``i`` of ``k``: all distinct."""
    import matplotlib

    cmap = matplotlib.colormaps["tab20" if k > 10 else "tab10"]
    styles = ("-", "--", ":", "-.")
    return {"color": cmap(i % cmap.N), "ls": styles[(i // cmap.N) % len(styles)]}


def _running_best(v: torch.Tensor, maximize: bool) -> torch.Tensor:
    return torch.cummax(v, 0).values if maximize else torch.cummin(v, 0).values


def draw_run(data: dict):
    """The figure of :func:`run_report`'s data: ``(fig, (ax, axk))``, the objective panel and the
    knob panel (matplotlib, Agg backend; close the figure when done)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(data["Y"])
    steps = torch.arange(1, n + 1).numpy()
    Y, X = data["Y"], data["X"]
    yu = data.get("objective_unit") or ""
    ku = data.get("unit") or ""
    ys = f" {yu}" if yu else ""
    fig, (ax, axk) = plt.subplots(2, 1, figsize=(10, 8.5), sharex=True, height_ratios=[3, 2])
    if data["noise"]:
        s = data["noise"]
        ax.fill_between(steps, (Y - s).numpy(), (Y + s).numpy(), color="C0", alpha=0.15,
                        label=f"noise band ±{s:g}{ys}")  # fmt: skip
    ax.plot(steps, Y.numpy(), ".", color="C0", label="reading")
    ax.plot(steps, _running_best(Y, data["maximize"]).numpy(), color="C0", label="best reading")
    if data["true"] is not None:
        t = data["true"]
        ax.plot(steps, t.numpy(), "x", ms=3, color="C2", label="true value (noise-free)")
        best_true = _running_best(t, data["maximize"]).numpy()
        ax.plot(steps, best_true, color="C2", label="best true value")
    if data.get("optimum") is not None:
        f_star = data["optimum"][1]
        ax.axhline(f_star, color="k", ls="--", lw=1,
                   label=f"true optimum {f_star:.4g}{ys} (simulated machine)")  # fmt: skip
    fit = data["fit"]
    if fit is not None:
        lo, hi = fit["value"] - 2 * fit["value_std"], fit["value"] + 2 * fit["value_std"]
        label = f"fitted optimum {fit['value']:.4g} ± {2 * fit['value_std']:.2g}{ys} (2σ)"
        ax.axhspan(lo, hi, color="C3", alpha=0.12, label=label)
        ax.axhline(fit["value"], color="C3", lw=1)
    ax.set_ylabel(f"objective ({yu})" if yu else "objective")
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    ax.grid(alpha=0.3)
    title = f"{data['path'].name}: {data['method']}, {n} of {data['budget']} evaluations"
    ax.set_title(f"{title} ({data['status']})")

    names = data["knob_names"]
    for i, name in enumerate(names):
        axk.plot(steps, X[:, i].numpy(), lw=1, label=name, **_knob_style(i, len(names)))
    if data["bounds"] is not None:
        for v in sorted(set(data["bounds"].flatten().tolist())):
            axk.axhline(v, color="k", ls="--", lw=0.8)
    if fit is not None:
        xs = n + 1 + 0.25 * torch.arange(len(names)).numpy() / max(1, len(names))
        for i in range(len(names)):
            axk.errorbar(xs[i], float(fit["center"][i]), yerr=2 * float(fit["center_std"][i]),
                         fmt="o", ms=3, capsize=2,
                         color=_knob_style(i, len(names))["color"])  # fmt: skip
        axk.annotate(
            "fitted centre ±2σ", (n + 1.3, axk.get_ylim()[1]), fontsize=8, va="top", ha="right"
        )
    axk.set_xlabel("evaluation")
    axk.set_ylabel(f"knob setting ({ku})" if ku else "knob setting")
    axk.grid(alpha=0.3)
    axk.legend(ncol=1 + len(names) // 16, fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    if data["notices"]:
        fig.text(0.01, 0.005, "\n".join(data["notices"][:6]), fontsize=7, va="bottom")
        fig.subplots_adjust(bottom=0.08 + 0.018 * min(6, len(data["notices"])))
    return fig, (ax, axk)


def plot_run(data: dict, path: str | Path) -> Path:
    """Draw :func:`run_report`'s data (:func:`draw_run`) into a PNG at ``path``; returns it."""
    import matplotlib.pyplot as plt

    fig, _ = draw_run(data)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path


def plot_compare(data: dict, path: str | Path) -> Path:
    """Draw :func:`compare_report`'s data into a PNG at ``path``; returns the path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    df = data["runs"]
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(12, 4.8))
    has_gain = "gain_fraction" in df and df["gain_fraction"].notna().any()
    col = "gain_fraction" if has_gain else "y"
    for k, (method, g) in enumerate(df.groupby("method", sort=False)):
        q = g.groupby("step")[col].quantile([0.25, 0.5, 0.75]).unstack()
        x = q.index.to_numpy() + 1
        ax.plot(x, q[0.5], color=f"C{k}",
                label=f"{method} ({g['machine_seed'].nunique()} machines)")  # fmt: skip
        ax.fill_between(x, q[0.25], q[0.75], color=f"C{k}", alpha=0.2)
        for _, run in g.groupby("machine_seed"):
            value = run["best_f_true"] if "best_f_true" in run else run["y"].cummax()
            ax2.plot(run["step"] + 1, value, color=f"C{k}", lw=0.8, alpha=0.7)
    ax.set_ylabel("gain fraction (median, IQR; 1 = optimum)" if has_gain
                  else "reading (mA/min; median, IQR)")  # fmt: skip
    ax2.set_ylabel("best noise-free loss rate so far (mA/min; each run)")
    for a in (ax, ax2):
        a.set_xlabel("evaluation")
        a.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.suptitle(f"{data['path']}")
    path = Path(path)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path
