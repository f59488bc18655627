"""The figures of :mod:`pigp_torch.reporting.report`: one run (:func:`draw_run`,
:func:`plot_run`) and a ``pigp compare`` folder (:func:`plot_compare`); matplotlib, Agg backend.
"""

from __future__ import annotations

from pathlib import Path

import torch

from pigp_torch._utils.units import display_unit


def _knob_style(i: int, k: int) -> dict:
    """Colour (and, beyond 20 knobs, line style) of knob ``i`` of ``k``: all distinct."""
    import matplotlib

    cmap = matplotlib.colormaps["tab20" if k > 10 else "tab10"]
    styles = ("-", "--", ":", "-.")
    return {"color": cmap(i % cmap.N), "ls": styles[(i // cmap.N) % len(styles)]}


def _running_best(v: torch.Tensor, maximize: bool) -> torch.Tensor:
    return torch.cummax(v, 0).values if maximize else torch.cummin(v, 0).values


def in_display_units(data: dict) -> dict:
    """:func:`run_report`'s data with the readings (their noise, true values, the true and the
    fitted optimum) and the observables in the unit a person reads
    (:func:`~pigp_torch._utils.units.display_unit`: a beam in m as µm); others unchanged."""
    k, unit = display_unit(data.get("objective_unit"))
    out = dict(data, objective_unit=unit)
    if k != 1.0:
        out["Y"] = k * data["Y"]
        out["noise"] = None if not data.get("noise") else k * data["noise"]
        out["true"] = None if data.get("true") is None else k * data["true"]
        if data.get("optimum") is not None:
            out["optimum"] = (data["optimum"][0], k * data["optimum"][1])
        fit = data.get("fit")
        if fit is not None:
            out["fit"] = dict(fit, value=k * fit["value"], value_std=k * fit["value_std"])
    obs, units = data.get("observables"), data.get("observable_units")
    if obs is not None and units and len(units) == obs.shape[1]:
        scales = [display_unit(u) for u in units]
        out["observables"] = obs * torch.tensor([f for f, _ in scales], dtype=obs.dtype)
        out["observable_units"] = [u for _, u in scales]
    return out


def _knob_groups(data: dict) -> list[tuple[str, list[int]]]:
    """``(unit, knob indices)`` per knob unit, in the knobs' order: one knob panel each (a
    linac's quadrupoles in 1/m^2 apart from its correctors in rad)."""
    names, per_knob = data["knob_names"], data.get("knob_units")
    if not per_knob or len(per_knob) != len(names):
        return [(data.get("unit") or "", list(range(len(names))))]
    groups: dict[str, list[int]] = {}
    for i, u in enumerate(per_knob):
        groups.setdefault(str(u), []).append(i)
    return list(groups.items())


def draw_run(data: dict):
    """The figure of :func:`run_report`'s data: ``(fig, (ax, axk, ...))``, the objective panel
    and one knob panel per knob unit (one for the SPEAR3 windings in A; the quadrupoles and the
    correctors of ARES-EA apart), readings in the unit a person reads (:func:`in_display_units`;
    matplotlib, Agg backend; close the figure when done)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    data = in_display_units(data)
    n = len(data["Y"])
    steps = torch.arange(1, n + 1).numpy()
    Y = data["Y"]
    yu = data.get("objective_unit") or ""
    ys = f" {yu}" if yu else ""
    groups = _knob_groups(data)
    fig, axes = plt.subplots(1 + len(groups), 1, figsize=(10, 8.5 + 2.5 * (len(groups) - 1)),
                             sharex=True, height_ratios=[3] + [2] * len(groups))  # fmt: skip
    ax = axes[0]
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

    for axk, (ku, idx) in zip(axes[1:], groups, strict=True):
        _draw_knobs(axk, data, idx, ku, steps)
    axes[-1].set_xlabel("evaluation")
    if data["notices"]:
        fig.text(0.01, 0.005, "\n".join(data["notices"][:6]), fontsize=7, va="bottom")
        fig.subplots_adjust(bottom=0.08 + 0.018 * min(6, len(data["notices"])))
    return fig, tuple(axes)


def _draw_knobs(axk, data: dict, idx: list[int], ku: str, steps) -> None:
    """The knob panel of the knobs ``idx`` (all in unit ``ku``): settings, their limits, and the
    fitted centre ±2σ."""
    names, X, fit, n = data["knob_names"], data["X"], data["fit"], len(data["Y"])
    for i in idx:
        axk.plot(steps, X[:, i].numpy(), lw=1, label=names[i], **_knob_style(i, len(names)))
    if data["bounds"] is not None:
        for v in sorted(set(data["bounds"][:, idx].flatten().tolist())):
            axk.axhline(v, color="k", ls="--", lw=0.8)
    if fit is not None:
        xs = n + 1 + 0.25 * torch.arange(len(names)).numpy() / max(1, len(names))
        for i in idx:
            axk.errorbar(xs[i], float(fit["center"][i]), yerr=2 * float(fit["center_std"][i]),
                         fmt="o", ms=3, capsize=2,
                         color=_knob_style(i, len(names))["color"])  # fmt: skip
        axk.annotate(
            "fitted centre ±2σ", (n + 1.3, axk.get_ylim()[1]), fontsize=8, va="top", ha="right"
        )
    axk.set_ylabel(f"knob setting ({ku})" if ku else "knob setting")
    axk.grid(alpha=0.3)
    axk.legend(ncol=1 + len(idx) // 16, fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))


def plot_run(data: dict, path: str | Path) -> Path:
    """Draw :func:`run_report`'s data (:func:`draw_run`) into a PNG at ``path``; returns it."""
    import matplotlib.pyplot as plt

    fig, _ = draw_run(data)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path


def plot_time(data: dict, path: str | Path) -> Path:
    """Draw the run against wall-clock time (:func:`~pigp_torch.reporting.timeline.draw_time`,
    readings in the unit a person reads) into a PNG at ``path``; returns it."""
    import matplotlib.pyplot as plt

    from pigp_torch.reporting.timeline import draw_time

    fig, _ = draw_time(in_display_units(data))
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
