r"""Xopt's side of the data: VOCS from knob bounds or a prior, and Xopt data frames.

Needs the optional extra ``xopt``.

**Data frames.** Xopt keeps one row per evaluation with the VOCS variables, constants and outputs
as columns, plus ``xopt_runtime`` and ``xopt_error``; :func:`to_xopt_dataframe` turns the table of
:func:`pigp_torch.optimize` into that form.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from typing import Any

import pandas as pd
import torch

try:
    from gest_api.vocs import (
        ContextualVariable,
        ContinuousVariable,
        MaximizeObjective,
        MinimizeObjective,
    )
    from xopt.vocs import VOCS
except ImportError as err:  # pragma: no cover - depends on the environment
    raise ImportError(
        "pigp_torch.integrations.xopt_vocs needs Xopt; install the extra: "
        "pip install 'pigp-torch[xopt]'"
    ) from err

from pigp_torch._utils import check_bounds
from pigp_torch.prior import PhysicsPrior

#: Columns Xopt's evaluator adds to every row.
XOPT_RUNTIME, XOPT_ERROR = "xopt_runtime", "xopt_error"


# ----------------------------------------------------------------------------- VOCS
def vocs_from_bounds(
    knob_names,
    bounds,
    *,
    objective: str = "loss_rate",
    maximize: bool = True,
    constants: Mapping[str, Any] | None = None,
) -> VOCS:
    r"""The Xopt VOCS of a tuning problem: one continuous variable per knob, one objective.

    Args:
        knob_names: ``d`` unique knob names, in the order of the columns of ``bounds`` (this is
            the order of ``vocs.variable_names`` and of the tensors :class:`XoptOptimizer`
            returns).
        bounds: ``2 x d`` knob bounds (row 0 lower, row 1 upper).
        objective: name of the objective output (default ``"loss_rate"``).
        maximize: ``MAXIMIZE`` (default: the loss rate rises as the beam gets smaller) or
            ``MINIMIZE``.
        constants: optional VOCS constants (name -> value) passed along with the variables.

    Returns:
        ``VOCS(variables={name: [lower, upper]}, objectives={objective: "MAXIMIZE"})``.

    Raises:
        ValueError: bounds of the wrong shape or empty, duplicate knob names, an objective name
            that clashes with a knob name.
    """
    if isinstance(knob_names, str):
        raise ValueError("knob_names must be a list of names, not one string")
    names = [str(n) for n in knob_names]
    if len(set(names)) != len(names):
        raise ValueError(f"knob names must be unique, got {names}")
    b = check_bounds(bounds)
    if b.shape[1] != len(names):
        raise ValueError(f"bounds must have shape (2, {len(names)}), got {tuple(b.shape)}")
    objective = str(objective)
    if objective in names:
        raise ValueError(f"objective name {objective!r} is also a knob name")
    variables = {
        n: [float(lo), float(hi)]
        for n, lo, hi in zip(names, b[0].tolist(), b[1].tolist(), strict=True)
    }
    return VOCS(
        variables=variables,
        objectives={objective: "MAXIMIZE" if maximize else "MINIMIZE"},
        constants=dict(constants or {}),
    )


def vocs_from_prior(prior: PhysicsPrior, bounds=None, **kwargs) -> VOCS:
    r"""The VOCS of the prior's knobs (:func:`vocs_from_bounds`).

    Args:
        prior: the physics prior; its ``knob_names`` name the variables (in this order).
        bounds: ``2 x d`` knob bounds in the prior's knob order (default ``prior.bounds``), e.g.
            a machine's ``bounds``.
        **kwargs: ``objective``, ``maximize``, ``constants`` of :func:`vocs_from_bounds`.

    Raises:
        ValueError: ``prior`` not a PhysicsPrior, or as :func:`vocs_from_bounds`.
    """
    if not isinstance(prior, PhysicsPrior):
        raise ValueError(f"prior must be a PhysicsPrior, got {type(prior).__name__}")
    return vocs_from_bounds(prior.knob_names, prior.bounds if bounds is None else bounds, **kwargs)


def single_objective(vocs: VOCS) -> tuple[str, bool]:
    """``(name, maximize)`` of the VOCS's only objective."""
    if vocs.n_objectives != 1:
        raise ValueError(f"need exactly one objective in the VOCS, got {vocs.objective_names}")
    name = vocs.objective_names[0]
    obj = vocs.objectives[name]
    if isinstance(obj, MaximizeObjective):
        return name, True
    if isinstance(obj, MinimizeObjective):
        return name, False
    raise ValueError(f"objective {name!r} must be MAXIMIZE or MINIMIZE, got {type(obj).__name__}")


def prior_as_dict(value: Any) -> dict[str, Any]:
    """A prior field of a generator as plain, validated data (a :class:`PhysicsPrior`, its
    dict form, or the path of its JSON file, e.g. typed into Badger's generator settings).

    Raises:
        ValueError: anything else, or a dict or file that is not a valid prior.
    """
    if isinstance(value, (str, os.PathLike)):
        try:
            return PhysicsPrior.load(value).to_dict()  # plain JSON, never a pickle
        except OSError as err:
            raise ValueError(f"cannot read the prior file {value}: {err}") from err
    if isinstance(value, PhysicsPrior):
        return value.to_dict()
    if isinstance(value, dict):
        return PhysicsPrior.from_dict(value).to_dict()  # validates every field
    raise ValueError(f"prior must be a PhysicsPrior or its dict, got {type(value).__name__}")


def continuous_bounds(vocs: VOCS) -> torch.Tensor:
    """``2 x d`` bounds of the VOCS variables (all must be plain continuous variables)."""
    bad = [
        n
        for n, v in vocs.variables.items()
        if not isinstance(v, ContinuousVariable) or isinstance(v, ContextualVariable)
    ]
    if bad:
        raise ValueError(f"only continuous (non-contextual) variables are supported; got {bad}")
    return check_bounds(torch.tensor([list(v.domain) for v in vocs.variables.values()]).T)


# ----------------------------------------------------------------------------- data frames
def to_xopt_dataframe(
    table: pd.DataFrame,
    vocs: VOCS,
    *,
    objective_column: str = "y",
    outputs: Mapping[str, str] | None = None,
    runtime_column: str | None = "eval_time_s",
) -> pd.DataFrame:
    r"""A pigp run log (the table of :func:`pigp_torch.optimize`) as Xopt data.

    Columns, in order: the VOCS variables (``vocs.variable_names``), the VOCS constants (their
    values), the outputs named by the VOCS, ``xopt_runtime`` (seconds of the evaluation, from
    ``runtime_column``; NaN if ``None``) and ``xopt_error`` (False). Index ``0 .. n-1`` (int64),
    as Xopt keeps it. Pass the result to ``Xopt(..., data=df)``, ``Xopt.add_data(df)`` or
    ``generator.add_data(df)`` to continue a run in Xopt / Badger.

    Args:
        table: one row per evaluation with one column per knob (named as the VOCS variables) and
            the observed objective.
        vocs: the VOCS of the problem.
        objective_column: table column holding the objective (default ``"y"``); it becomes the
            VOCS's only objective. Ignored if ``outputs`` is given.
        outputs: ``{vocs output name: table column}`` for several outputs.
        runtime_column: table column copied into ``xopt_runtime``.

    Raises:
        ValueError: knob or output columns missing, several objectives without ``outputs``, an
            output not named by the VOCS, non-finite knob values.
    """
    if not isinstance(table, pd.DataFrame):
        raise ValueError(f"table must be a pandas DataFrame, got {type(table).__name__}")
    names = list(vocs.variable_names)
    missing = [n for n in names if n not in table.columns]
    if missing:
        raise ValueError(f"table lacks knob columns {missing} named by the VOCS")
    if outputs is None:
        if vocs.n_objectives != 1:
            raise ValueError(
                f"the VOCS has objectives {vocs.objective_names}: map them with outputs="
            )
        outputs = {vocs.objective_names[0]: objective_column}
    unknown = [k for k in outputs if k not in vocs.output_names]
    if unknown:
        raise ValueError(f"outputs {unknown} are not named by the VOCS {vocs.output_names}")
    absent = [c for c in outputs.values() if c not in table.columns]
    if absent:
        raise ValueError(f"table lacks output columns {absent}")

    n = len(table)
    out = pd.DataFrame(index=pd.RangeIndex(n).astype("int64"))
    for name in names:
        out[name] = table[name].to_numpy(dtype="float64")
    if not torch.isfinite(torch.as_tensor(out[names].to_numpy())).all():
        raise ValueError("table has non-finite knob values")
    for name, value in vocs.constants.items():
        out[name] = value.value
    for name, column in outputs.items():
        out[name] = table[column].to_numpy(dtype="float64")
    if runtime_column is not None and runtime_column in table.columns:
        out[XOPT_RUNTIME] = table[runtime_column].to_numpy(dtype="float64")
    else:
        out[XOPT_RUNTIME] = float("nan")
    out[XOPT_ERROR] = False
    return out
