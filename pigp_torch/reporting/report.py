r"""Figures for the logbook: one online run from its run log, or a ``pigp compare`` folder.

:func:`run_report` reads a JSON-lines run log (:mod:`pigp_torch.data.runlog`) and draws, against the
evaluation number:

* the readings with the noise band (:math:`\pm\sigma_n`: the simulated machine's noise, else the
  prior's, else the ``noise`` argument; no band when none is known), the best reading so far and,
  for a run on the simulated ring, the noise-free value at every setting, its best so far and the
  machine's true optimum within the run's bounds (a converged run reaches that line); for a run
  on the simulated ARES-EA linac, the noise-free objective at every setting;
* the knob trajectories in knob units with their limits (the run's bounds), each knob in its own
  colour (``tab20``; beyond 20 knobs the line style changes too), and for
  ``pigp-physics`` the fitted centre of the physics form at the end of the run with
  :math:`\pm 2\sigma` (Laplace) per knob;
* the fitted optimum (``pigp-physics``: the form refitted to all readings, its predicted value
  :math:`\pm 2\sigma` at the best setting inside the box);
* the run's notices: sessions (resumes), discarded readings, knobs reaching a limit, the end
  status and reason, a fitted centre outside the box;
* in the summary, for a machine that measures observables with its objective (a screen's beam
  numbers), those of the best reading with their units.

:func:`compare_report` draws a ``pigp compare`` / ``pigp demo`` folder (``runs.csv``): the gain
fraction (median and interquartile range over machines) and the best noise-free value per method.

:func:`write_report` writes the figure as PNG and a self-contained HTML page (the PNG embedded as
base64, the notices and a summary as text; no external resources).

Every number carries its unit: the objective's (``objective_unit`` of the run file, default
mA/min) and the knobs' (``knob_unit``, default A); a log written before run files named units
gets those defaults.
"""

from __future__ import annotations

import base64
import html
import math
from pathlib import Path

import torch

from pigp_torch._utils import DTYPE
from pigp_torch.data.runlog import read_log
from pigp_torch.loop.config.schema import logged_units
from pigp_torch.reporting.figures import (  # noqa: F401
    draw_run,
    in_display_units,
    plot_compare,
    plot_run,
    plot_time,
)
from pigp_torch.reporting.timeline import timeline


def _load_run_config(records):
    """The logged configuration (``None`` when the header has none or it no longer loads)."""
    from pigp_torch.loop.run import logged_config

    try:
        return logged_config(records)
    except Exception:  # an older log, an edited header, a prior file moved: draw without it
        return None


def _fitted_optimum(config, X: torch.Tensor, Y: torch.Tensor) -> dict | None:
    """``pigp-physics``: refit the form to all readings; centre, its std, value at the optimum."""
    from pigp_torch.loop.run import build_optimizer

    if config is None or config.method.name != "pigp-physics" or len(Y) < 2:
        return None
    opt = build_optimizer(config)
    model = opt.model
    model.fit(X, Y)
    x_hat, active = model.box_optimum()
    with torch.no_grad():
        mu, sd = model.predict(x_hat.reshape(1, -1))
    d = model.dim
    return {
        "center": model.center(),
        "center_std": model.cov[:d, :d].diagonal().clamp_min(0).sqrt(),
        "x_hat": x_hat,
        "active": active,
        "value": float(mu[0]),
        "value_std": float(sd[0]),
    }


def run_report(
    path: str | Path, *, noise: float | None = None, fit: bool = True, progress=None
) -> dict:
    r"""What the figure of one run shows, from its run log.

    Runs torch on one thread (:func:`~pigp_torch._utils.pool.one_torch_thread`, as ``pigp demo``
    does; restored afterwards): the true optimum's search is many small batched evaluations.

    Args:
        path: the run log.
        noise: :math:`\sigma_n` of the readings when neither the simulated machine nor the prior
            gives it (objective units).
        fit: refit ``pigp-physics``'s form to show the fitted optimum (one MAP fit).
        progress: called with one line of text before each step that takes a while (building
            the simulated machine, its optimum's search, the refit); default: silent.

    Returns:
        a dict: ``path``, ``method``, ``knob_names``, ``unit`` (knob unit), ``objective_unit``,
        ``bounds`` (``2 x d`` or ``None``), ``maximize``, ``X`` (``n x d``), ``Y``
        (``n``), ``noise`` (or ``None``), ``true`` (noise-free values, simulated runs only, else
        ``None``), ``optimum`` (simulated, maximized runs: ``(x_star, f_star)``, the machine's
        true optimum within the run's bounds; else ``None``), ``fit``
        (:func:`_fitted_optimum` or ``None``), ``notices`` (list of strings), ``budget``,
        ``status``, ``observables`` (``n x m`` what each reading also measured, or ``None``),
        ``observable_names`` and ``observable_units`` (the header's, ``[]`` without),
        ``timeline`` (:func:`~pigp_torch.reporting.timeline.timeline`: the readings' times and
        the tracked unknowns).

    Raises:
        FileNotFoundError: no such log.
        ValueError: not a run log, or it holds no evaluation.
    """
    from pigp_torch._utils.pool import one_torch_thread

    records = read_log(path)
    if not records.evaluations:
        raise ValueError(f"{path}: the run log holds no evaluation yet")
    with one_torch_thread():
        return _run_report(path, records, noise, fit, progress or (lambda text: None))


def _run_report(path, records, noise, fit, say) -> dict:
    """:func:`run_report` on the records read (``say``: the progress callable)."""
    h = records.header
    X, Y = records.X(), records.Y()
    names = records.knob_names or [f"x{i}" for i in range(X.shape[1])]
    bounds = torch.tensor(h["bounds"], dtype=DTYPE) if h.get("bounds") else None
    config = _load_run_config(records)
    maximize = bool(h.get("maximize", True))
    objective_unit, unit = logged_units(h)
    true = optimum = None
    sigma = noise
    truth = _true_objective(config, say)
    if truth is not None:
        sigma = sigma if truth.noise is None else truth.noise
        true = torch.as_tensor(truth.values(X), dtype=DTYPE)
        if truth.peak is not None and maximize and bounds is not None:
            say(f"searching its true optimum within the run's bounds (L-BFGS-B from the run's "
                f"{min(OPTIMUM_STARTS, len(X))} best settings) ...")  # fmt: skip
            optimum = _true_optimum(truth.peak, bounds, X, true)
    elif config is not None and config.prior is not None and sigma is None:
        from pigp_torch.prior import PhysicsPrior

        sigma = PhysicsPrior.load(config.prior).noise
    notices = _notices(records, X, bounds, names)
    if fit and config is not None and config.method.name == "pigp-physics":
        say(f"refitting pigp-physics's form to the {len(Y)} readings ...")
    fitted = _fitted_optimum(config, X, Y) if fit else None
    if fitted is not None and bool(fitted["active"].any()):
        knobs = [names[i] for i in fitted["active"].nonzero().flatten().tolist()]
        notices.append(f"fitted centre outside the box: optimum on the limit of {knobs}")
    end = records.last_end
    return {
        "path": Path(path),
        "method": h.get("method", "?"),
        "knob_names": names,
        "unit": unit,
        "knob_units": h.get("knob_units"),  # one per knob where the machine has them
        "objective_unit": objective_unit,
        "optimum": optimum,
        "bounds": bounds,
        "maximize": maximize,
        "X": X,
        "Y": Y,
        "noise": sigma,
        "true": true,
        "fit": fitted,
        "notices": notices,
        "budget": (records.starts[-1].get("budget") if records.starts else None) or len(Y),
        "status": "running (no end record)" if end is None else end["status"],
        "observables": records.observables(),
        "observable_names": records.observable_names,
        "observable_units": records.observable_units,
        "timeline": timeline(records.evaluations),
    }


#: starts of the true optimum's search: the run's settings with the largest noise-free values
OPTIMUM_STARTS = 3


def _true_objective(config, say):
    """The noise-free objective of the run's simulated machine, from its machine kind
    (:meth:`~pigp_torch.machines.MachineKind.true_objective`); ``None`` without one (a live
    machine, or a log without its configuration)."""
    from pigp_torch.loop.run import machine_kind

    kind = None if config is None else machine_kind(config)
    return None if kind is None else kind.true_objective(config, say)


def _true_optimum(peak, bounds: torch.Tensor, X: torch.Tensor, true: torch.Tensor):
    """The largest value of the simulated machine's differentiable noise-free objective
    ``peak`` within the run's ``bounds``: L-BFGS-B
    (:func:`~pigp_torch._utils.multistart.find_optimum`) from the :data:`OPTIMUM_STARTS`
    settings of the run (``X``, ``n x d``) with the largest noise-free values ``true`` (``n``).

    A run's best settings lie on the slope of the maximum it climbs, so a few starts there
    suffice where a wide search (8 Sobol starts, the zero knobs and the run's best setting)
    spends its cost on starts far from it (one L-BFGS-B problem over all starts: the cost grows
    with their number). ``tests/test_report.py`` checks that both find the same optimum.

    Returns:
        ``(x_star, f_star)``: ``d`` knob setting and its value (objective units).
    """
    from pigp_torch._utils.multistart import find_optimum

    best = true.argsort(descending=True)[:OPTIMUM_STARTS]
    return find_optimum(peak, bounds, n_starts=0, x_init=X[best])


def _notices(records, X: torch.Tensor, bounds, names) -> list[str]:
    """The run's events, in order, as short lines (steps counted from 1)."""
    out = []
    for s in records.starts[1:]:
        out.append(f"resumed at evaluation {int(s.get('first_step', 0)) + 1}")
    for s in records.starts:  # a noise measured at a start (the run file stated none)
        noise = s.get("noise")
        if isinstance(noise, dict) and noise.get("source") == "measured":
            unit = logged_units(records.header)[0]
            out.append(f"reading noise {noise['sigma']:.4g} {unit} measured at the start from "
                       f"{noise.get('n')} readings at the initial setting")  # fmt: skip
    for r in records.discarded:
        out.append(f"reading discarded at evaluation {int(r['step']) + 1}: {r.get('reason', '')}")
    for r in records.notices:
        out.append(f"evaluation {int(r['step']) + 1}: {r.get('message', '')}")
    if bounds is not None and len(X):
        span = bounds[1] - bounds[0]
        at = (X <= bounds[0] + 1e-6 * span) | (X >= bounds[1] - 1e-6 * span)
        for i in at.any(0).nonzero().flatten().tolist():
            step = int(at[:, i].nonzero()[0])
            out.append(f"{names[i]} reached its limit at evaluation {step + 1}")
    end = records.last_end
    if end is not None:
        reason = f": {end['reason']}" if end.get("reason") else ""
        out.append(f"ended {end['status']}{reason}; knobs restored to {end.get('restored_to')}")
    return out


def compare_report(folder: str | Path) -> dict:
    """What the figure of a ``pigp compare`` folder shows (its ``runs.csv``).

    Raises:
        FileNotFoundError: no ``runs.csv`` in ``folder``.
    """
    import pandas as pd

    folder = Path(folder)
    csv = folder / "runs.csv"
    if not csv.is_file():
        raise FileNotFoundError(f"{folder} has no runs.csv (not a pigp compare folder)")
    from pigp_torch.data.tables import read_table

    df = read_table(csv)  # the plain column names (the file's headers carry units)
    notes = []
    summary = folder / "summary.csv"
    if summary.is_file():
        notes = pd.read_csv(summary).to_string(index=False, float_format="%.3g").splitlines()
    return {"path": folder, "runs": df, "notices": notes}


def html_page(title: str, png: Path | list[Path], lines: list[str]) -> str:
    """A self-contained HTML page: ``title``, the PNG(s) embedded as base64, ``lines`` as
    text."""
    pngs = [png] if isinstance(png, (str, Path)) else list(png)
    images = "\n".join(
        "<img alt='report' style='max-width:100%' src='data:image/png;base64,"
        f"{base64.b64encode(Path(p).read_bytes()).decode('ascii')}'>"
        for p in pngs
    )
    items = "\n".join(f"<li>{html.escape(s)}</li>" for s in lines)
    return (
        "<!DOCTYPE html>\n<html><head><meta charset='utf-8'>"
        f"<title>{html.escape(title)}</title></head>\n<body style='font-family:sans-serif'>\n"
        f"<h1>{html.escape(title)}</h1>\n{images}\n<ul style='font-family:monospace'>\n{items}\n"
        "</ul>\n</body></html>\n"
    )


def write_report(
    target: str | Path, out: str | Path | None = None, *, noise: float | None = None, progress=None
) -> tuple[Path, Path]:
    r"""Write ``<out>.png`` and ``<out>.html`` for a run log or a ``pigp compare`` folder.

    Args:
        target: a run log (file) or a folder with ``runs.csv``.
        out: path without suffix (default: ``<log without .jsonl>_report`` next to the log, or
            ``<folder>/report``).
        noise, progress: as in :func:`run_report`.

    Returns:
        ``(png, html)`` paths (a run log's page also embeds ``<out>_time.png``: the run
        against wall-clock time with the tracked unknowns,
        :func:`~pigp_torch.reporting.timeline.draw_time`).

    Raises:
        FileNotFoundError, ValueError: as :func:`run_report` / :func:`compare_report`.
    """
    target = Path(target)
    if target.is_dir():
        data = compare_report(target)
        base = Path(out) if out is not None else target / "report"
        png = plot_compare(data, base.with_suffix(".png"))
        title = f"pigp compare: {target}"
        lines = data["notices"]
    else:
        data = run_report(target, noise=noise, progress=progress)
        base = Path(out) if out is not None else target.with_name(target.stem + "_report")
        png = plot_run(data, base.with_suffix(".png"))
        pngs = [png, plot_time(data, base.with_name(base.name + "_time.png"))]
        title = f"pigp run: {target.name} ({data['method']})"
        lines = [*_summary(data), *data["notices"]]
    page = base.with_suffix(".html")
    page.write_text(html_page(title, pngs if not target.is_dir() else png, lines),
                    encoding="utf-8")  # fmt: skip
    return png, page


def _summary(data: dict) -> list[str]:
    """The page's text lines: best reading (and true value), true and fitted optimum, with units
    (readings in the unit a person reads, :func:`in_display_units`)."""
    data = in_display_units(data)
    Y = data["Y"]
    yu = data.get("objective_unit") or ""
    ys = f" {yu}" if yu else ""
    i = int(Y.argmax() if data["maximize"] else Y.argmin())
    lines = [f"best reading {float(Y[i]):.6g}{ys} at evaluation {i + 1} of {len(Y)}"]
    obs, obs_names = data.get("observables"), data.get("observable_names") or []
    if obs is not None and len(obs_names) == obs.shape[1]:
        units = data.get("observable_units") or [""] * len(obs_names)
        values = ", ".join(
            f"{n} = {float(v):.6g}{' ' + u if u else ''}"
            for n, v, u in zip(obs_names, obs[i], units, strict=True)
        )
        lines.append(f"observables of the best reading: {values}")
    if data["noise"]:
        lines.append(f"reading noise σ = {data['noise']:g}{ys}")
    if data["true"] is not None:
        t = data["true"]
        j = int(t.argmax() if data["maximize"] else t.argmin())
        lines.append(f"best true value {float(t[j]):.6g}{ys} at evaluation {j + 1}")
        if data.get("optimum") is not None:
            f_star = data["optimum"][1]
            lines.append(
                f"true optimum of the simulated machine {f_star:.6g}{ys} (best true value "
                f"{100 * float(t[j]) / f_star:.1f} % of it)"
            )
    fit = data["fit"]
    if fit is not None and math.isfinite(fit["value"]):
        lines.append(f"fitted optimum {fit['value']:.6g} ± {2 * fit['value_std']:.3g}{ys} (2σ)")
    per_knob = data.get("knob_units")
    if per_knob and len(per_knob) == len(data["knob_names"]):
        units = ", ".join(f"{n} in {u}" for n, u in zip(data["knob_names"], per_knob, strict=True))
        lines.append(f"knob settings: {units}; the objective in {yu or 'its own unit'}")
    elif data.get("unit"):
        lines.append(f"knob settings in {data['unit']}; the objective in {yu or 'its own unit'}")
    return lines
