r"""The CSV files of a ``pigp compare`` / ``pigp demo`` folder with units in their headers.

``runs.csv`` and ``summary.csv`` name each column with its unit, ``name [unit]``: a loss rate
``y [mA/min]``, a knob ``01G-QSS4 [A]``, a summary's ``best_f_true_median [mA/min]`` and
``steps_to_95_median [evaluations]``; columns whose name already says the unit (``ask_time_s``)
or that have none (``method``, ``gain_fraction``, a fraction) keep their names.
:func:`read_table` reads such a file back with the plain names (``y``, ``01G-QSS4``), the ones
the code uses, and reads a file written before the units the same.
"""

from __future__ import annotations

import re
from pathlib import Path

import pandas as pd

#: columns in the loss rate's unit (the objective of every simulated ring)
LOSS_RATE_COLUMNS = ("y", "f_true", "best_f_true", "f0", "f_star")
_UNIT = re.compile(r"^(.*) \[[^\]]*\]$")


def _unit_of(column: str, objective_unit: str, knobs: dict[str, str]) -> str | None:
    if column in knobs:
        return knobs[column]
    base = re.sub(r"_(median|q25|q75)$", "", column)
    if base in LOSS_RATE_COLUMNS:
        return objective_unit
    if base.startswith(("steps_to_", "steps_within")):
        return "evaluations"
    return None  # a name that says its unit (ask_time_s), a fraction, a count, a label


def with_units(df: pd.DataFrame, knob_units: dict[str, str], *, objective_unit: str = "mA/min"):
    """``df`` with each column that has a unit renamed ``name [unit]`` (a copy): the knobs
    (``knob_units``: name -> unit), the loss rates (``objective_unit``) and the counts of
    evaluations."""
    names = {}
    for c in df.columns:
        unit = _unit_of(str(c), objective_unit, dict(knob_units))
        names[c] = f"{c} [{unit}]" if unit else c
    return df.rename(columns=names)


def plain_names(df: pd.DataFrame) -> pd.DataFrame:
    """``df`` with ``name [unit]`` columns renamed ``name`` (a copy)."""
    return df.rename(columns=lambda c: _UNIT.sub(r"\1", str(c)))


def read_table(path: str | Path, **kwargs) -> pd.DataFrame:
    """A ``runs.csv`` / ``summary.csv`` (:func:`pandas.read_csv` with ``kwargs``) with the
    plain column names the code uses (``y``, not ``y [mA/min]``)."""
    return plain_names(pd.read_csv(path, **kwargs))
