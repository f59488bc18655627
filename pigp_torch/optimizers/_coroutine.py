r"""Ask/tell wrapper for optimization algorithms written as generator coroutines.

Direct-search algorithms (Nelder–Mead, RCDS) are easiest to read as straight-line code that calls
the objective whenever it needs a value. Written as a Python generator, each call becomes

.. code-block:: python

    f = yield u  # "please measure the objective at u", resumed with the measured value

and :class:`CoroutineOptimizer` turns the generator into the ask/tell protocol of
:mod:`pigp_torch.optimizers.base`: :meth:`~CoroutineOptimizer.ask` resumes the generator up to its
next ``yield`` and returns the proposed point, :meth:`~CoroutineOptimizer.tell` stores the value
that the next ``ask`` sends in. The loop (simulator, EPICS machine, benchmark) can therefore pause
for as long as a measurement takes.

Conventions inside the generator:

* points ``u`` are numpy float64 vectors in the unit cube, :math:`u = (x - x_{lo}) / (x_{hi} -
  x_{lo})`, and must lie in :math:`[0, 1]^d` (the wrapper clamps only round-off);
* the values sent in are to be MINIMIZED: :math:`f = -y` when maximizing, :math:`f = y` otherwise;
* the generator never returns (it restarts instead), so ``ask`` can always answer.
"""

from __future__ import annotations

from collections.abc import Generator

import numpy as np
import torch

from pigp_torch._utils import DTYPE
from pigp_torch.optimizers.base import AskTellOptimizer

#: Type of an algorithm coroutine: yields unit-cube points, is sent the values to minimize.
Coroutine = Generator[np.ndarray, float, None]


def feasible_interval(u: np.ndarray, direction: np.ndarray) -> tuple[float, float]:
    r"""Range of step lengths that keep a line inside the unit cube.

    Args:
        u: ``d`` point in :math:`[0, 1]^d`.
        direction: ``d`` direction (not necessarily normalized).

    Returns:
        ``(t_lo, t_hi)`` with :math:`t_{lo} \le 0 \le t_{hi}`, the largest interval such that
        :math:`u + t\,v \in [0, 1]^d` for all :math:`t \in [t_{lo}, t_{hi}]`.
    """
    t_lo, t_hi = -np.inf, np.inf
    for ui, vi in zip(u, direction, strict=True):
        if vi > 0:
            t_hi = min(t_hi, (1.0 - ui) / vi)
            t_lo = max(t_lo, -ui / vi)
        elif vi < 0:
            t_hi = min(t_hi, -ui / vi)
            t_lo = max(t_lo, (1.0 - ui) / vi)
    return min(t_lo, 0.0), max(t_hi, 0.0)


class CoroutineOptimizer(AskTellOptimizer):
    r"""Base class: runs :meth:`_algorithm` as a coroutine behind ``ask``/``tell``.

    Protocol (stricter than Bayesian optimization, which accepts arbitrary extra points):

    * the first ``tell(x0, y0)`` sets the start point, which must lie inside ``bounds``;
    * ``ask()`` before that raises ``RuntimeError``; calling ``ask()`` again before telling returns
      the same pending point;
    * every later ``tell`` must report the pending point (within ``point_tol`` times the knob range
      per knob), otherwise ``ValueError``; the recorded ``x`` is the one told.

    Subclasses implement :meth:`_algorithm`.

    Args:
        bounds: ``2 x d`` knob bounds.
        maximize: maximize (default) or minimize the objective.
    """

    #: Tolerance, as a fraction of each knob's range, for matching a told point to the asked one.
    point_tol: float = 1e-9

    def __init__(self, bounds, *, maximize: bool = True) -> None:
        super().__init__(bounds, maximize=maximize)
        self._coroutine: Coroutine | None = None
        self._pending: torch.Tensor | None = None
        self._to_send: float | None = None

    def _algorithm(self, u0: np.ndarray, f0: float) -> Coroutine:  # pragma: no cover - abstract
        """The algorithm: start at ``u0`` (unit cube) with value ``f0`` (to minimize)."""
        raise NotImplementedError

    # -- coordinate maps -------------------------------------------------------------------------
    @property
    def _width(self) -> torch.Tensor:
        return self.bounds[1] - self.bounds[0]

    def _to_unit(self, x: torch.Tensor) -> np.ndarray:
        u = ((x - self.bounds[0]) / self._width).numpy()
        return np.clip(u, 0.0, 1.0)

    def _from_unit(self, u: np.ndarray) -> torch.Tensor:
        u = torch.as_tensor(np.clip(np.asarray(u, dtype=np.float64), 0.0, 1.0), dtype=DTYPE)
        x = self.bounds[0] + u * self._width
        return torch.minimum(torch.maximum(x, self.bounds[0]), self.bounds[1])

    def _internal(self, y: float) -> float:
        return -float(y) if self.maximize else float(y)

    # -- protocol --------------------------------------------------------------------------------
    def tell(self, x, y: float) -> None:
        r"""Report the objective ``y`` at ``x`` (``d``): the start point first, then each asked one.

        Raises:
            ValueError: wrong dimension, non-finite values, a start point outside ``bounds``, a
                point other than the one asked, or a tell without a pending ``ask``.
        """
        x = self._check_point(x)
        tol = self.point_tol * self._width
        if self._coroutine is None:
            outside = ((x < self.bounds[0] - tol) | (x > self.bounds[1] + tol)).nonzero()
            if outside.numel():
                bad = outside.flatten().tolist()
                raise ValueError(f"start point lies outside the bounds for knob indices {bad}")
            super().tell(x, y)
            self._coroutine = self._algorithm(self._to_unit(x), self._internal(y))
            return
        if self._pending is None:
            raise ValueError(
                f"{type(self).__name__} only accepts the point returned by ask(); call ask() first"
            )
        if not bool(((x - self._pending).abs() <= tol).all()):
            raise ValueError(
                f"told point {x.tolist()} differs from the asked point {self._pending.tolist()}"
            )
        super().tell(x, y)
        self._to_send = self._internal(y)
        self._pending = None

    def ask(self) -> torch.Tensor:
        r"""Next knob setting to measure, a ``d`` float64 tensor inside ``bounds``.

        Raises:
            RuntimeError: no start point was told yet.
        """
        if self._coroutine is None:
            raise RuntimeError(
                f"{type(self).__name__}.ask() needs a start point: tell(x0, y0) the current "
                "setting and its measured objective first"
            )
        if self._pending is None:
            if self._to_send is None:
                u = next(self._coroutine)
            else:
                u = self._coroutine.send(self._to_send)
                self._to_send = None
            self._pending = self._from_unit(u)
        return self._pending.clone()
