"""The constant prior mean of a physics-informed GP from its option value."""

from __future__ import annotations

import math


def prior_mean_value(prior, mean, *, what: str = "a float") -> float:
    r"""The constant prior mean of ``mean`` (objective units): ``"f_inf"`` :math:`f_\infty` of
    ``prior`` (the paper), ``"zero"`` (Fig. 2c) or a finite float.

    Raises:
        ValueError: another string, or a value that is not a finite float (``what`` names the
            other accepted kinds in the message).
    """
    if isinstance(mean, str):
        if mean not in ("f_inf", "zero"):
            raise ValueError(f'mean must be "f_inf", "zero" or {what}, got {mean!r}')
        return float(prior.f_inf) if mean == "f_inf" else 0.0
    try:
        value = float(mean)
    except (TypeError, ValueError):
        raise ValueError(f'mean must be "f_inf", "zero" or {what}, got {mean!r}') from None
    if not math.isfinite(value):
        raise ValueError(f"mean must be finite, got {value}")
    return value
