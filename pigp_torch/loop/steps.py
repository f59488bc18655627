r"""The steps of a run between its start and its end: ask -> evaluate -> tell with the run log
and the table kept in step, and the small helpers of :func:`~pigp_torch.loop.optimize`."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable

import torch

from pigp_torch._utils import DTYPE
from pigp_torch._utils import utc_now as _utc_now
from pigp_torch.data.runlog import RunRecords, tell
from pigp_torch.loop.signals import RunAborted, SignalGuard

_RESERVED = ("step", "y", "method", "ask_time_s", "eval_time_s")


def knob_columns(knob_names, d: int) -> list[str]:
    """The table's knob columns: ``knob_names`` (``d``, checked), ``x0 .. x{d-1}`` for ``None``."""
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


def observables_of(machine) -> list[float] | None:
    """The observables of a machine's last reading (``last_observables``, e.g. the four beam
    numbers on a screen) as floats; ``None`` for a machine without them."""
    obs = machine.last_observables
    if obs is None:
        return None
    return [float(v) for v in torch.as_tensor(obs, dtype=DTYPE).reshape(-1).tolist()]


@dataclasses.dataclass(frozen=True)
class StepContext:
    r"""What every step of one run reads, built once at its start
    (:func:`~pigp_torch.loop.session.run_all_steps`).

    Attributes:
        evaluate: ``(x, step) -> (y, reads)``: move to ``x`` (``d``) and read the objective
            (``reads``: the attempts it took).
        names: the ``d`` knob columns; label: the ``method`` column.
        log: the run log (``None``: none); the start record goes there first.
        x_initial: ``d`` restore target (``None`` for a plain callable); x_found, rb_found: the
            setpoints and readbacks found at the start (logged when they differ / exist).
        reading_info: ``() -> dict | None``: the machine's description of its last reading.
        observables: ``() -> list | None``: the observables of the last reading, logged with it
            and told to an optimizer that fits them.
        objective_floor: a reading below it aborts the run (``None``: no floor).
        callback: called with each new row (a dict) after its step, or ``None``.
        progress: show a tqdm progress bar.
        start_fields: more fields of the start record (the noise in force).
        stop: a track run's ``() -> bool``, asked before each step after the first: true ends
            the steps (its time limit); ``None``: none.
        record: a track run's ``() -> dict``: more fields of each evaluation record (its
            ``tracked``); ``None``: none.
    """

    evaluate: Callable[..., tuple[float, int]]
    names: list[str]
    label: str
    log: object = None
    x_initial: torch.Tensor | None = None
    x_found: torch.Tensor | None = None
    rb_found: torch.Tensor | None = None
    reading_info: Callable[[], object] = lambda: None
    observables: Callable[[], list[float] | None] = lambda: None
    objective_floor: float | None = None
    callback: Callable[[dict], None] | None = None
    progress: bool = False
    start_fields: dict = dataclasses.field(default_factory=dict)
    stop: Callable[[], bool] | None = None
    record: Callable[[], dict] | None = None


def _log_start(ctx: StepContext, budget: int, first: int) -> None:
    """The start record: the restore target, and the knobs found when they differ from it (and
    ``ctx.start_fields``, the noise in force)."""
    extra = dict(ctx.start_fields)
    if ctx.x_found is not None and ctx.x_found is not ctx.x_initial:
        extra["found_knobs"] = ctx.x_found.tolist()
    if ctx.rb_found is not None:  # the knobs above are setpoints; their readbacks then
        extra["found_readbacks"] = ctx.rb_found.tolist()
    ctx.log.log_start(ctx.x_initial, budget=budget, first_step=first, **extra)


def run_steps(
    ctx: StepContext, optimizer, x0, rows: list[dict], *, first: int, budget: int,
    guard: SignalGuard,
) -> None:  # fmt: skip
    """Steps ``first .. budget-1`` of :func:`~pigp_torch.loop.optimize` from ``x0`` (``d``, the
    setting of step 0), appended to ``rows``; what each step reads is ``ctx``."""
    log, names, label, stop, record = ctx.log, ctx.names, ctx.label, ctx.stop, ctx.record
    if log is not None:
        _log_start(ctx, budget, first)
    bar = None
    if ctx.progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=budget, initial=first, desc=str(label))
    try:
        x = x0
        seen = len(optimizer.notices)  # notices of a replay are not repeated
        for step in range(first, budget):
            if step > 0 and stop is not None and stop():
                break
            t_set = time.time()
            ask_time = 0.0
            notices: list[dict] = []
            if step > 0:
                t0 = time.perf_counter()
                x = torch.as_tensor(optimizer.ask(), dtype=DTYPE).reshape(-1)
                ask_time = time.perf_counter() - t0
                notices = list(optimizer.notices[seen:])
                seen += len(notices)
            if log is not None:
                for notice in notices:  # the optimizer's own findings, before the move
                    log.write("notice", step=step, time=_utc_now(), **notice)
            t0 = time.perf_counter()
            y, reads = ctx.evaluate(x, step=step)  # every move a checked ramp
            info = ctx.reading_info()
            obs = ctx.observables()
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
            if ctx.callback is not None:
                ctx.callback(dict(row))
            if bar is not None:
                bar.update(1)
            floor = ctx.objective_floor
            if floor is not None and y < floor:
                raise RunAborted(f"objective {y:.6g} at step {step} is below the floor {floor:g}")
    finally:
        if bar is not None:
            bar.close()
