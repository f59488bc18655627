r"""The units a person reads: a length in metres is shown in micrometres.

Run logs, CSV files and the machines keep SI values (a beam size or a distance on a screen in
m); what is printed or drawn for a person goes through :func:`display_unit`, so that an ARES-EA
beam reads ``y = 0.823 µm`` rather than ``y = 8.23e-07 m``. A unit not listed is shown as it is.
"""

from __future__ import annotations

#: unit -> (factor, unit shown): the value shown is ``factor * value``.
DISPLAY_UNITS: dict[str, tuple[float, str]] = {"m": (1e6, "µm")}


def display_unit(unit: str | None) -> tuple[float, str]:
    """``(factor, shown_unit)`` for values in ``unit`` (``(1.0, unit)`` for any other unit;
    ``None`` reads as ``""``)."""
    unit = unit or ""
    return DISPLAY_UNITS.get(unit, (1.0, unit))
