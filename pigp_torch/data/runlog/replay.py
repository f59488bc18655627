r"""Replaying a run log: the optimizer rebuilt from the logged evaluations, and the table rows."""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import torch

from pigp_torch._utils import DTYPE
from pigp_torch.data.runlog.format import ReplayError, floats
from pigp_torch.data.runlog.reader import RunRecords


def _evaluations(records) -> list[dict]:
    if isinstance(records, RunRecords):
        return list(records.evaluations)
    records = list(records)
    for k, r in enumerate(records):
        if r.get("step", k) != k:
            raise ValueError(f"evaluation records must have steps 0, 1, ...; got {r.get('step')}")
    return records


def replay(
    optimizer,
    records: RunRecords | Iterable[Mapping[str, Any]],
    *,
    tol: float = 1e-6,
    progress: bool = False,
) -> int:
    r"""Rebuild an optimizer's state from logged evaluations; returns how many were told.

    ``optimizer`` must be fresh (nothing told), built exactly as in the logged run (same class,
    bounds, options, seed, prior). Step 0 is told as the start point; for every later record the
    optimizer is asked for its next point, which must equal the logged ``x`` within ``tol`` times
    each knob's range, and then told the logged ``(x, y)``. Asking is what makes the rebuilt state
    exact: direct-search coroutines advance their generators, model factories with internal state
    (e.g. warm-started hyperparameters) see the same sequence of calls, and the check proves the
    log and the optimizer agree. A record's logged ``observables`` are told with it to an
    optimizer that fits them (``uses_observables``). The cost is one ``ask`` per record (a GP
    fit and an acquisition optimization for BayesOpt).

    Args:
        optimizer: a fresh :class:`~pigp_torch.optimizers.AskTellOptimizer` (its declared
            ``n_told``, ``bounds`` and ``uses_observables`` are read).
        records: a :class:`RunRecords` or evaluation records (dicts with ``x`` and ``y``, in step
            order).
        tol: allowed difference between asked and logged points, a fraction of the knob range.
        progress: tqdm bar over the records.

    Raises:
        ReplayError: the optimizer already holds data, or an asked point differs from the logged
            one (the message names the step and both points).
    """
    evaluations = _evaluations(records)
    if optimizer.n_told:
        raise ReplayError("replay needs a fresh optimizer (this one has already been told data)")
    width = optimizer.bounds[1] - optimizer.bounds[0]
    it = evaluations
    if progress:
        from tqdm.auto import tqdm

        it = tqdm(evaluations, desc="replaying the run log")
    for k, rec in enumerate(it):
        x = torch.tensor(floats(rec["x"]), dtype=DTYPE)
        if k > 0:
            asked = torch.as_tensor(optimizer.ask(), dtype=DTYPE).reshape(-1)
            limit = tol * width
            if asked.shape != x.shape or not bool(((asked - x).abs() <= limit).all()):
                raise ReplayError(
                    f"replay diverged at step {k}: the optimizer asks {asked.tolist()} but the "
                    f"log holds {x.tolist()}; the method, its options, seed or prior differ from "
                    "the logged run"
                )
        try:
            obs = rec.get("observables")
            tell(optimizer, x, float(rec["y"]), None if obs is None else floats(obs))
        except ValueError as err:
            raise ReplayError(f"replay failed at step {k}: {err}") from err
    return len(evaluations)


def tell(optimizer, x: torch.Tensor, y: float, observables: Sequence[float] | None) -> None:
    """``optimizer.tell(x, y)``; with ``observables=`` (an ``m`` float64 tensor) when the
    optimizer fits them (``uses_observables``) and the reading has them (the loop and
    :func:`replay` tell alike)."""
    if observables is not None and optimizer.uses_observables:
        optimizer.tell(x, y, observables=torch.tensor(list(observables), dtype=DTYPE))
    else:
        optimizer.tell(x, y)


def evaluation_rows(
    records: RunRecords | Sequence[Mapping[str, Any]], knob_names: Sequence[str], method: str
) -> list[dict]:
    """Logged evaluations as rows of the :func:`pigp_torch.optimize` table."""
    rows = []
    for rec in _evaluations(records):
        row = {"step": int(rec["step"]), **dict(zip(knob_names, floats(rec["x"]), strict=True))}
        row.update(
            y=float(rec["y"]),
            method=method,
            ask_time_s=float(rec.get("ask_time_s", 0.0)),
            eval_time_s=float(rec.get("eval_time_s", 0.0)),
        )
        rows.append(row)
    return rows
