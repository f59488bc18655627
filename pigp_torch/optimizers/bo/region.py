r"""The region part of the Bayesian-optimization core: where the next setting may lie.

:class:`TrustRegion` is the trust box of half-width ``step_limit`` (a fraction of each knob's
half-range) around a centre chosen among the told points, optionally within a travel limit of the
last told point. With :math:`c` the centre, :math:`\ell, h` the knob bounds and :math:`s` =
``step_limit``:

.. math:: \max\!\big(\ell,\; c - s\,\tfrac{h - \ell}{2}\big) \le x \le
          \min\!\big(h,\; c + s\,\tfrac{h - \ell}{2}\big),

i.e. with knobs normalized to :math:`[-1, 1]` the box is :math:`c \pm s` per knob.
"""

from __future__ import annotations

import torch

from pigp_torch._utils import DTYPE

#: Centre rules: the told point with the best noisy reading (first one on ties), or with the
#: highest posterior mean (a single lucky reading cannot move the box).
TRUST_CENTERS = ("best_observed", "best_mean")


def trust_box(bounds: torch.Tensor, center: torch.Tensor, step_limit: float | None) -> torch.Tensor:
    r"""The ``2 x d`` search box of half-width ``step_limit`` (a fraction of each knob's
    half-range) around ``center`` (clamped into ``bounds``), intersected with ``bounds``
    (module docstring); ``step_limit=None`` gives the whole box."""
    lower, upper = bounds
    if step_limit is None:
        return bounds.clone()
    c = torch.minimum(torch.maximum(center, lower), upper)
    half = step_limit * (upper - lower) / 2
    return torch.stack([torch.maximum(lower, c - half), torch.minimum(upper, c + half)])


def clamp_to_box(x: torch.Tensor, box: torch.Tensor) -> torch.Tensor:
    """``x`` (``d``) clamped into the ``2 x d`` ``box`` (the final guard against round-off)."""
    return torch.minimum(torch.maximum(x, box[0]), box[1])


def check_step_limit(step_limit) -> float | None:
    """``step_limit`` as a float: positive and finite, or ``None``."""
    if step_limit is not None and not (0.0 < float(step_limit) < float("inf")):
        raise ValueError(f"step_limit must be positive and finite (or None), got {step_limit}")
    return None if step_limit is None else float(step_limit)


def _travel_limit(value, d: int) -> torch.Tensor | None:
    """``None`` or a ``d`` tensor of positive finite fractions of the half-range."""
    if value is None:
        return None
    t = torch.as_tensor(value, dtype=DTYPE).reshape(-1)
    if t.numel() == 1:
        t = t.expand(d).clone()
    if t.numel() != d or not bool(torch.isfinite(t).all() and (t > 0).all()):
        raise ValueError(f"travel_limit must be positive and finite, one value or {d}: {value}")
    return t


class TrustRegion:
    r"""Trust box around a told point, optionally within a travel limit of the last one.

    Args:
        bounds: ``2 x d`` knob bounds.
        step_limit: trust-box half-width as a fraction of each knob's half-range, or ``None``
            (the whole box).
        center: ``"best_observed"`` or ``"best_mean"`` (:data:`TRUST_CENTERS`).
        travel_limit: a hard step limit (a fraction of each knob's half-range: one value or
            ``d``) around the last told point, or ``None``. The search box is the trust box
            intersected with the travel box; where the two do not overlap the travel box alone
            is used, so a proposal never moves a knob farther than the limit.
    """

    def __init__(self, bounds, step_limit=0.3, center="best_observed", travel_limit=None):
        if center not in TRUST_CENTERS:
            raise ValueError(f"trust_center must be one of {TRUST_CENTERS}, got {center!r}")
        self.bounds = bounds
        self.step_limit = check_step_limit(step_limit)
        self.center_rule = center
        self.travel_limit = _travel_limit(travel_limit, bounds.shape[1])

    def center(self, X: torch.Tensor, Y: torch.Tensor, posterior) -> torch.Tensor:
        """The centre among the told ``X: n x d`` (readings ``Y: n``, internal sign)."""
        if self.center_rule == "best_observed":
            return X[int(Y.argmax())]
        return X[int(torch.as_tensor(posterior.train_mean(X)).argmax())]

    def trust_box(self, center: torch.Tensor) -> torch.Tensor:
        """The ``2 x d`` trust box around ``center`` (:func:`trust_box`)."""
        return trust_box(self.bounds, center, self.step_limit)

    def box(self, center: torch.Tensor, last: torch.Tensor) -> torch.Tensor:
        """The ``2 x d`` box the acquisition is maximized in: the trust box of ``center``,
        within ``travel_limit`` of ``last`` (the last told point) when one is set."""
        box = self.trust_box(center)
        if self.travel_limit is None:
            return box
        half = self.travel_limit * (self.bounds[1] - self.bounds[0]) / 2
        travel = torch.stack(
            [torch.maximum(self.bounds[0], last - half), torch.minimum(self.bounds[1], last + half)]
        )
        lower, upper = torch.maximum(box[0], travel[0]), torch.minimum(box[1], travel[1])
        apart = lower > upper
        return torch.stack(
            [torch.where(apart, travel[0], lower), torch.where(apart, travel[1], upper)]
        )
