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


class AskTellOptimizer:
    r"""Base class: stores bounds, the direction of optimization and the evaluation history.

    Subclasses implement :meth:`ask` and may extend :meth:`tell` (call ``super().tell`` first).

    The loop (:func:`pigp_torch.loop.optimize`) reads these attributes directly: ``name`` (the
    table's ``method`` column by default), ``dim`` (``d``), ``maximize``, ``notices`` (what
    :meth:`notify` recorded; the loop logs each new one) and ``uses_observables`` (``True``:
    :meth:`tell` also takes ``observables=``, the ``m`` observables of the reading; default
    ``False``).

    Args:
        bounds: ``2 x d`` knob bounds.
        maximize: maximize (default) or minimize the objective.
    """

    name = "base"
    uses_observables = False

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

    def recommend(self) -> torch.Tensor:
        """The optimizer's current estimate of the best setting (``d``, knob units).

        Default: the best observed point (:meth:`best`). An optimizer with a model of the
        machine overrides it with the model's optimum *now* (on a drifting machine the best
        reading may be hours old). A track run leaves the knobs here at its end
        (``restore: estimate``); the Xopt generator exposes it.

        Raises:
            RuntimeError: nothing told yet.
        """
        return self.best()[0]

    def tracked(self) -> dict[str, tuple[float, str]]:
        """The tracked unknowns' current estimates: ``{name: (value, unit)}`` (e.g.
        ``{"beam_x": (1.2e-4, "m")}``). Default ``{}``: nothing tracked. The loop logs them
        with each evaluation (field ``tracked``); the report and the dashboard draw them
        against time."""
        return {}
