r"""The ask/tell protocol shared by every optimizer.

One protocol lets the same loop drive a simulator, an EPICS machine or a benchmark:

* ``tell(x, y)`` reports one measurement. The FIRST ``tell`` defines the start point (the loop
  measures the machine's current settings before asking for anything); later tells report the
  points the optimizer asked for (Bayesian optimization also accepts arbitrary extra points).
* ``ask()`` returns the next knob setting, a ``d`` float64 tensor inside ``bounds``.
* Every optimizer MAXIMIZES the objective (the loss rate rises as the beam gets smaller); pass
  ``maximize=False`` to minimize instead.
"""

from __future__ import annotations

import torch

from pigp_torch._utils import DTYPE, check_bounds


def check_ucb_options(beta, step_limit) -> tuple[float, float | None]:
    """Validate the UCB trade-off ``beta`` (finite, >= 0) and the trust-box ``step_limit``
    (positive and finite, or ``None``); return them as floats."""
    if not (float(beta) >= 0.0 and float(beta) < float("inf")):
        raise ValueError(f"beta must be finite and >= 0, got {beta}")
    if step_limit is not None and not (0.0 < float(step_limit) < float("inf")):
        raise ValueError(f"step_limit must be positive and finite (or None), got {step_limit}")
    return float(beta), None if step_limit is None else float(step_limit)


def check_search_options(
    trust_center: str, centers, num_restarts: int, raw_samples: int, min_restarts: int = 1
) -> None:
    """Validate a trust-box centre rule (one of ``centers``) and the acquisition-search counts
    (``num_restarts >= min_restarts`` and ``raw_samples >= num_restarts``)."""
    if trust_center not in centers:
        raise ValueError(f"trust_center must be one of {centers}, got {trust_center!r}")
    if int(num_restarts) < min_restarts or int(raw_samples) < int(num_restarts):
        raise ValueError(
            f"need num_restarts >= {min_restarts} and raw_samples >= num_restarts; "
            f"got {num_restarts}, {raw_samples}"
        )


def trust_box(bounds: torch.Tensor, center: torch.Tensor, step_limit: float | None) -> torch.Tensor:
    r"""The ``2 x d`` search box of half-width ``step_limit`` (a fraction of each knob's
    half-range) around ``center`` (clamped into ``bounds``), intersected with ``bounds``.

    .. math:: \max\!\big(\ell,\; c - s\,\tfrac{h - \ell}{2}\big) \le x \le
              \min\!\big(h,\; c + s\,\tfrac{h - \ell}{2}\big)

    ``step_limit=None`` gives the whole box.
    """
    lower, upper = bounds
    if step_limit is None:
        return bounds.clone()
    c = torch.minimum(torch.maximum(center, lower), upper)
    half = step_limit * (upper - lower) / 2
    return torch.stack([torch.maximum(lower, c - half), torch.minimum(upper, c + half)])


class AskTellOptimizer:
    r"""Base class: stores bounds, the direction of optimization and the evaluation history.

    Subclasses implement :meth:`ask` and may extend :meth:`tell` (call ``super().tell`` first).

    Args:
        bounds: ``2 x d`` knob bounds.
        maximize: maximize (default) or minimize the objective.
    """

    name = "base"

    def __init__(self, bounds, *, maximize: bool = True) -> None:
        self.bounds = check_bounds(bounds)
        self.maximize = bool(maximize)
        self.X: list[torch.Tensor] = []
        self.Y: list[float] = []
        self.notices: list[dict] = []

    @property
    def dim(self) -> int:
        return self.bounds.shape[1]

    @property
    def n_told(self) -> int:
        return len(self.Y)

    def _check_point(self, x) -> torch.Tensor:
        x = torch.as_tensor(x, dtype=DTYPE).reshape(-1)
        if x.numel() != self.dim:
            raise ValueError(f"point has {x.numel()} entries, the optimizer has {self.dim} knobs")
        if not torch.isfinite(x).all():
            raise ValueError("point contains NaN or inf")
        return x

    def tell(self, x, y: float) -> None:
        """Record one measurement ``y`` at knob setting ``x`` (``d``)."""
        x = self._check_point(x)
        y = float(y)
        if y != y or y in (float("inf"), float("-inf")):
            raise ValueError(f"objective value must be finite, got {y}")
        self.X.append(x)
        self.Y.append(y)

    def notify(self, kind: str, message: str, **data) -> dict:
        """Record a notice for the operator: ``{"kind", "message", "at_told", **data}``
        (``at_told``: the measurements told so far). The loop writes each new notice to the
        run log and the progress line; returns the notice."""
        notice = {"kind": str(kind), "message": str(message), "at_told": self.n_told, **data}
        self.notices.append(notice)
        return notice

    def ask(self) -> torch.Tensor:  # pragma: no cover - abstract
        raise NotImplementedError

    def best(self) -> tuple[torch.Tensor, float]:
        """Best observed ``(x, y)`` so far (largest y when maximizing)."""
        if not self.Y:
            raise RuntimeError("no measurements yet: tell() the start point first")
        ys = torch.tensor(self.Y, dtype=DTYPE)
        i = int(ys.argmax() if self.maximize else ys.argmin())
        return self.X[i].clone(), self.Y[i]
