r"""The steps of a run between its start and its end: ask -> evaluate -> tell with the run log
and the table kept in step, and the small helpers of :func:`~pigp_torch.loop.optimize`."""

from __future__ import annotations

import time

import torch

from pigp_torch._utils import DTYPE
from pigp_torch._utils import utc_now as _utc_now
from pigp_torch.data.runlog import RunRecords, tell
from pigp_torch.loop.signals import RunAborted, SignalGuard

_RESERVED = ("step", "y", "method", "ask_time_s", "eval_time_s")


def knob_columns(knob_names, objective, d: int) -> list[str]:
    if knob_names is None:
        knob_names = getattr(objective, "knob_names", None)
    names = [f"x{i}" for i in range(d)] if knob_names is None else [str(n) for n in knob_names]
    if len(names) != d:
        raise ValueError(f"{len(names)} knob names for {d} knobs")
    if len(set(names)) != d:
        raise ValueError("knob names must be unique")
    clash = sorted(set(names) & set(_RESERVED))
    if clash:
        raise ValueError(f"knob names {clash} clash with the table columns {_RESERVED}")
    return names


def logged_initial_knobs(resume) -> torch.Tensor | None:
    """The initial knobs of a resumed run's first start record (``None`` if not logged)."""
    if not isinstance(resume, RunRecords):
        return None
    for start in resume.starts:
        knobs = start.get("initial_knobs")
        if knobs is not None:
            return torch.tensor([float(v) for v in knobs], dtype=DTYPE)
    return None


def best_row(rows: list[dict], names: list[str], maximize: bool) -> dict | None:
    """``{"step", "x", "y"}`` of the best row (first on ties), ``None`` without rows."""
    if not rows:
        return None
    ys = torch.tensor([r["y"] for r in rows], dtype=DTYPE)
    b = rows[int(ys.argmax() if maximize else ys.argmin())]
    return {"step": b["step"], "x": [b[n] for n in names], "y": b["y"]}


def observables_of(objective) -> list[float] | None:
    """The observables of a machine's last reading (``last_observables``, e.g. the four beam
    numbers on a screen) as floats; ``None`` for a machine (or callable) without them."""
    obs = getattr(objective, "last_observables", None)
    if obs is None:
        return None
    return [float(v) for v in torch.as_tensor(obs, dtype=DTYPE).reshape(-1).tolist()]


def _log_start(log, x_initial, x_found, rb_found, budget: int, first: int, extra) -> None:
    """The start record: the restore target, and the knobs found when they differ from it (and
    ``extra``, the noise in force)."""
    extra = dict(extra)
    if x_found is not None and x_found is not x_initial:
        extra["found_knobs"] = x_found.tolist()
    if rb_found is not None:  # the knobs above are setpoints; their readbacks then
        extra["found_readbacks"] = rb_found.tolist()
    log.log_start(x_initial, budget=budget, first_step=first, **extra)


def _progress_bar(progress: bool, budget: int, first: int, label):
    """A tqdm bar of the steps (``None`` without ``progress``)."""
    if not progress:
        return None
    from tqdm.auto import tqdm

    return tqdm(total=budget, initial=first, desc=str(label))


def run_steps(
    evaluate,
    optimizer,
    x0,
    first,
    budget,
    rows,
    *,
    names,
    label,
    log,
    x_initial,
    x_found,
    reading_info,
    observables=lambda: None,
    rb_found=None,
    callback,
    progress,
    objective_floor,
    guard: SignalGuard,
    start_fields=(),
    stop=None,
    record=None,
) -> None:
    """Steps ``first .. budget-1`` of :func:`~pigp_torch.loop.optimize`, appended to ``rows``.
    ``observables()``: those of the evaluation's reading (the last one taken) or ``None``, logged
    with it and told to an optimizer that fits them; ``start_fields``: in the start record; a
    track run's ``stop()`` (true before a step after the first ends the steps) and ``record()``
    (more fields of each evaluation record)."""
    if log is not None:
        _log_start(log, x_initial, x_found, rb_found, budget, first, start_fields)
    bar = _progress_bar(progress, budget, first, label)
    try:
        x = x0
        seen = len(getattr(optimizer, "notices", ()))  # notices of a replay are not repeated
        for step in range(first, budget):
            if step > 0 and stop is not None and stop():
                break
            t_set, ask_time, notices = time.time(), 0.0, []
            if step > 0:
                t0 = time.perf_counter()
                x = torch.as_tensor(optimizer.ask(), dtype=DTYPE).reshape(-1)
                ask_time = time.perf_counter() - t0
                notices = list(getattr(optimizer, "notices", ())[seen:])
                seen += len(notices)
            for notice in notices if log is not None else ():  # its findings, before the move
                log.write("notice", step=step, time=_utc_now(), **notice)
            t0 = time.perf_counter()
            y, reads = evaluate(x, step=step)  # every move a checked ramp
            info = reading_info()
            obs = observables()
            eval_time = time.perf_counter() - t0
            row = {"step": step, **dict(zip(names, x.tolist(), strict=True))}
            row.update(y=y, method=label, ask_time_s=ask_time, eval_time_s=eval_time)
            if notices:
                row["notices"] = [n["message"] for n in notices]
            with guard.held():  # a signal never splits the log record from the table row
                if log is not None:  # on disk before the optimizer hears of it
                    log.log_evaluation(
                        step, x, y, reads=reads, t_set=t_set, t_read=time.time(),
                        ask_time_s=ask_time, eval_time_s=eval_time,
                        **({"reading": info} if isinstance(info, dict) else {}),
                        **({"observables": obs} if obs is not None else {}),
                        **(record() if record is not None else {}),
                    )  # fmt: skip
                rows.append(row)
            t0 = time.perf_counter()
            tell(optimizer, x, y, obs)
            row["ask_time_s"] = ask_time + (time.perf_counter() - t0)
            if callback is not None:
                callback(dict(row))
            if bar is not None:
                bar.update(1)
            if objective_floor is not None and y < objective_floor:
                raise RunAborted(
                    f"objective {y:.6g} at step {step} is below the floor {objective_floor:g}"
                )
    finally:
        if bar is not None:
            bar.close()
