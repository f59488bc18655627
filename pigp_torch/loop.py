r"""The optimization loop: measure the start point, then ask -> evaluate -> tell until the budget.

The loop is the only place that talks to both an optimizer and a machine; it records every
evaluation in a tidy table and, on a :class:`~pigp_torch.machine.base.Machine`, puts the knobs
back to a safe setting when it ends or fails.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable

import pandas as pd
import torch

from pigp_torch._utils import DTYPE, as_knob_tensor
from pigp_torch.machine.base import Machine, ramp

RESTORE_MODES = ("initial", "best", "none")
_RESERVED = ("step", "y", "method", "ask_time_s", "eval_time_s")


def _knob_columns(knob_names, objective, d: int) -> list[str]:
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


def optimize(
    objective,
    optimizer,
    x0=None,
    budget: int = 100,
    *,
    knob_names=None,
    method: str | None = None,
    progress: bool = False,
    callback: Callable[[dict], None] | None = None,
    restore: str = "initial",
) -> pd.DataFrame:
    r"""Run an ask/tell optimizer on a machine or a function for ``budget`` evaluations.

    Step 0 evaluates ``x0`` and tells it (the first tell defines the optimizer's start); steps
    ``1 .. budget-1`` each ask, evaluate and tell. The budget counts every evaluation, ``x0``
    included.

    On a :class:`~pigp_torch.machine.base.Machine` (``set`` then ``read``) the knobs found at
    the start (``get()``) are remembered and, at the end:

    * ``restore="initial"`` (default, the safe choice): the initial knobs are set back;
    * ``restore="best"``: the best *observed* point is set (the loop's records, in the optimizer's
      direction ``optimizer.maximize``);
    * ``restore="none"``: the knobs are left where they are.

    The start point is reached with :func:`~pigp_torch.machine.base.ramp` (steps within the
    machine's ``max_step``); every later setting is a single ``set``, which the machine may refuse.
    If an exception escapes (including ``KeyboardInterrupt``) the initial knobs are set back
    (unless ``restore="none"``) and the exception is re-raised; a failure of that restore is
    reported as a warning so that it does not hide the original error. Moves are made with
    :func:`~pigp_torch.machine.base.ramp`, so a machine's ``max_step`` is respected. A plain
    callable ``objective(x) -> float`` is never restored.

    Args:
        objective: a ``Machine`` or a callable ``x (d) -> float``.
        optimizer: an ask/tell optimizer (:class:`~pigp_torch.optimizers.base.AskTellOptimizer`).
        x0: ``d`` start point; ``None`` uses the machine's current knobs.
        budget: total number of evaluations (>= 1).
        knob_names: column names for the knobs (default: the machine's, else ``x0..x{d-1}``).
        method: value of the ``method`` column (default ``optimizer.name``).
        progress: show a tqdm progress bar.
        callback: called with each row (a dict) after its step.
        restore: ``"initial"``, ``"best"`` or ``"none"``.

    Returns:
        a DataFrame with one row per evaluation and columns ``step`` (0..budget-1), one float64
        column per knob, ``y`` (observed objective), ``method``, ``ask_time_s`` (optimizer time for
        the ask and tell of that step) and ``eval_time_s``.

    Raises:
        ValueError: bad budget, restore mode, start point or knob names.
    """
    if int(budget) != budget or budget < 1:
        raise ValueError(f"budget must be a positive integer, got {budget}")
    budget = int(budget)
    if restore not in RESTORE_MODES:
        raise ValueError(f"restore must be one of {RESTORE_MODES}, got {restore!r}")
    is_machine = isinstance(objective, Machine)
    if not is_machine and not callable(objective):
        raise ValueError("objective must be a Machine or a callable x -> float")
    x_initial = torch.as_tensor(objective.get(), dtype=DTYPE).clone() if is_machine else None
    if x0 is None:
        if not is_machine:
            raise ValueError("x0 is required when the objective is a plain callable")
        x0 = x_initial
    if not isinstance(x0, torch.Tensor):  # lists/arrays straight to float64, not via float32
        x0 = torch.as_tensor(x0, dtype=DTYPE)
    d = getattr(optimizer, "dim", None) or x0.numel()
    x0 = as_knob_tensor(x0.reshape(-1), d, name="x0")[0][0]
    names = _knob_columns(knob_names, objective, d)
    label = method if method is not None else getattr(optimizer, "name", type(optimizer).__name__)
    maximize = bool(getattr(optimizer, "maximize", True))

    def evaluate(x: torch.Tensor, first: bool) -> float:
        if is_machine:
            if first:
                ramp(objective, x)  # reach the start point within the machine's max_step
            else:
                objective.set(x)
            return float(objective.read())
        return float(objective(x))

    rows: list[dict] = []
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=budget, desc=str(label))
    try:
        x = x0
        ask_time = 0.0
        for step in range(budget):
            if step > 0:
                t0 = time.perf_counter()
                x = torch.as_tensor(optimizer.ask(), dtype=DTYPE).reshape(-1)
                ask_time = time.perf_counter() - t0
            t0 = time.perf_counter()
            y = evaluate(x, step == 0)
            eval_time = time.perf_counter() - t0
            t0 = time.perf_counter()
            optimizer.tell(x, y)
            ask_time += time.perf_counter() - t0
            row = {"step": step, **dict(zip(names, x.tolist(), strict=True))}
            row.update(y=y, method=label, ask_time_s=ask_time, eval_time_s=eval_time)
            rows.append(row)
            if callback is not None:
                callback(dict(row))
            if bar is not None:
                bar.update(1)
    except BaseException:
        if is_machine and restore != "none":
            try:
                ramp(objective, x_initial)
            except Exception as err:  # report, but let the original error through
                warnings.warn(
                    f"could not restore the initial knobs after a failure: {err!r}", stacklevel=2
                )
        raise
    finally:
        if bar is not None:
            bar.close()

    if is_machine and restore != "none":
        if restore == "initial":
            ramp(objective, x_initial)
        else:
            ys = torch.tensor([r["y"] for r in rows], dtype=DTYPE)
            best = rows[int(ys.argmax() if maximize else ys.argmin())]
            ramp(objective, torch.tensor([best[n] for n in names], dtype=DTYPE))

    table = pd.DataFrame(rows, columns=["step", *names, "y", "method", "ask_time_s", "eval_time_s"])
    return table.astype({"step": "int64", **dict.fromkeys(names, "float64"), "y": "float64"})
