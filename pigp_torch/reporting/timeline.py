r"""A run against wall-clock time: the readings and the optimizer's tracked unknowns.

Every evaluation record holds its wall-clock times (``t_read``, s since the epoch) and, in a track
run, ``tracked`` (the optimizer's tracked unknowns, ``{name: [value, unit]}``). :func:`timeline`
turns them into time since the run's first reading, in a unit chosen from the run's length
(:func:`time_unit`: s up to 2 min, min up to 2 h, h beyond), and one series per tracked unknown in
the unit a person reads (:func:`~pigp_torch._utils.units.display_unit`: a beam position logged in
m shown in µm). :func:`draw_time` draws them: the objective against time, then one panel per
unit of the tracked unknowns (one-shot runs, which track nothing, get the objective panel only).
The report (:mod:`~pigp_torch.reporting.report`) and the dashboard show the same.
"""

from __future__ import annotations

import math

from pigp_torch._utils.units import display_unit

#: ``(largest span in s, unit, s per unit)``: the time axis' unit by the run's length.
TIME_UNITS = ((120.0, "s", 1.0), (7200.0, "min", 60.0), (math.inf, "h", 3600.0))


def time_unit(span_s: float) -> tuple[str, float]:
    """``(unit, s per unit)`` of a time axis spanning ``span_s`` seconds."""
    for limit, unit, scale in TIME_UNITS:
        if span_s <= limit:
            return unit, scale
    return TIME_UNITS[-1][1:]  # pragma: no cover - the last limit is infinite


def timeline(evaluations: list[dict]) -> dict:
    """The run against time, from its evaluation records.

    Returns:
        ``{"t": [...], "time_unit": str, "tracked": {name: {"unit": str, "values": [...]}}}``:
        ``t`` the time of each reading since the first, in ``time_unit`` (``None`` for a record
        without ``t_read``); ``values`` one per evaluation in the displayed ``unit`` (``None``
        where the record has no estimate of that unknown).
    """
    stamps = [r.get("t_read") for r in evaluations]
    known = [float(s) for s in stamps if isinstance(s, (int, float))]
    t0 = min(known) if known else 0.0
    unit, scale = time_unit(max(known) - t0 if known else 0.0)
    t = [None if not isinstance(s, (int, float)) else (float(s) - t0) / scale for s in stamps]
    tracked: dict[str, dict] = {}
    for i, r in enumerate(evaluations):
        for name, pair in (r.get("tracked") or {}).items():
            value, logged_unit = pair
            k, shown = display_unit(str(logged_unit))
            entry = tracked.setdefault(name, {"unit": shown, "scale": k, "values": []})
            entry["values"].extend([None] * (i - len(entry["values"])))
            entry["values"].append(None if value is None else entry["scale"] * float(value))
    for entry in tracked.values():
        entry["values"].extend([None] * (len(evaluations) - len(entry["values"])))
        del entry["scale"]
    return {"t": t, "time_unit": unit, "tracked": tracked}


def unit_groups(tracked: dict) -> list[tuple[str, list[str]]]:
    """``(unit, names)`` of the tracked unknowns, one group per unit, in first-seen order."""
    groups: dict[str, list[str]] = {}
    for name, entry in tracked.items():
        groups.setdefault(entry["unit"], []).append(name)
    return list(groups.items())


def draw_time(data: dict):
    """The figure against time of :func:`~pigp_torch.reporting.report.run_report`'s data
    (readings in their displayed unit; ``data["timeline"]`` from :func:`timeline`):
    ``(fig, axes)``, the objective panel then one panel per tracked unit (matplotlib, Agg
    backend; close the figure when done)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    line = data["timeline"]
    groups = unit_groups(line["tracked"])
    fig, axes = plt.subplots(1 + len(groups), 1, figsize=(10, 4 + 2.5 * len(groups)),
                             sharex=True, squeeze=False)  # fmt: skip
    axes = axes[:, 0]
    t = [math.nan if v is None else v for v in line["t"]]
    yu = data.get("objective_unit") or ""
    axes[0].plot(t, data["Y"].tolist(), ".", color="C0", label="reading")
    if data.get("true") is not None:
        axes[0].plot(t, data["true"].tolist(), "x", ms=3, color="C2",
                     label="true value (noise-free)")  # fmt: skip
    axes[0].set_ylabel(f"objective ({yu})" if yu else "objective")
    axes[0].set_title(f"{data['path'].name}: {data['method']} against time ({data['status']})")
    for ax, (unit, names) in zip(axes[1:], groups, strict=True):
        for name in names:
            ys = [math.nan if v is None else v for v in line["tracked"][name]["values"]]
            ax.plot(t, ys, lw=1.2, label=name)
        ax.set_ylabel(f"tracked ({unit})" if unit else "tracked")
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    axes[-1].set_xlabel(f"time since the first reading ({line['time_unit']})")
    return fig, tuple(axes)
