r"""Nelder–Mead restarted at a fixed period from the re-measured best setting.

On a drifting machine a best reading goes stale: the value it was measured at belongs to the
machine of some readings ago, and a simplex that converged keeps polishing an optimum that has
moved. The plain remedy of a control room is to start the search again every so often from the
best setting, measured afresh. :class:`NelderMeadRestart` does exactly that, with the simplex of
:class:`~pigp_torch.optimizers.NelderMead` (same coefficients, initial size and convergence
restarts):

* the readings are cut into segments of ``period`` readings: segment :math:`k` holds the readings
  :math:`t = kP, \dots, (k+1)P - 1` (:math:`P` = ``period``; reading 0 is the start setting);
* reading :math:`t = kP` for :math:`k \ge 1` re-measures the best setting of segment :math:`k-1`
  (the best of the readings since the last restart, the re-measurement that opened it included),
  and a fresh simplex is built around it with that fresh value as its first vertex; old readings
  are never compared with new ones;
* :meth:`NelderMeadRestart.recommend` is the setting of the most recent re-measurement (before
  the first one: the best reading so far).

Every point stays inside the bounds (the search runs in the unit cube, as Nelder–Mead's).
"""

from __future__ import annotations

import numpy as np
import torch

from pigp_torch.optimizers._coroutine import Coroutine
from pigp_torch.optimizers.nelder_mead import NelderMead, nelder_mead

#: Default restart period in readings: six fresh searches in a 300-reading run; long enough for a
#: 10-knob simplex (11 vertices) to take a few dozen steps, short against a drift that moves the
#: optimum by its width over the run.
DEFAULT_PERIOD = 50


class NelderMeadRestart(NelderMead):
    r"""Nelder–Mead restarted every ``period`` readings from the re-measured best setting.

    Args:
        bounds: ``2 x d`` knob bounds.
        period: readings per segment, ``>= d + 2`` (the start vertex, ``d`` simplex vertices
            and at least one step); default :data:`DEFAULT_PERIOD` (50).
        **options: ``initial_simplex_size``, ``maximize``, ``adaptive``, ``xatol``, ``fatol``
            of :class:`~pigp_torch.optimizers.NelderMead` (same defaults).

    Attributes:
        restarts: one ``(n_told, x, y)`` per restart: the reading index of the re-measurement,
            the re-measured ``d`` setting and its fresh value (objective units).

    Raises:
        ValueError: ``period < d + 2`` or a bad Nelder–Mead option.
    """

    name = "nelder-mead-restart"

    def __init__(self, bounds, *, period: int = DEFAULT_PERIOD, **options) -> None:
        super().__init__(bounds, **options)
        if int(period) != period or int(period) < self.dim + 2:
            raise ValueError(f"period must be an integer >= d + 2 = {self.dim + 2}, got {period}")
        self.period = int(period)
        self.restarts: list[tuple[int, torch.Tensor, float]] = []
        self._remeasuring = False

    def _algorithm(self, u0: np.ndarray, f0: float) -> Coroutine:
        period = self.period

        def simplex(u, f):
            return nelder_mead(
                u, f, size=self.initial_simplex_size, adaptive=self.adaptive,
                xatol=self.xatol, fatol=self.fatol,
            )  # fmt: skip

        best_u, best_f = np.array(u0, dtype=np.float64), float(f0)
        while True:  # one pass per segment of `period` readings
            search = simplex(best_u, best_f)
            u = next(search)
            for k in range(1, period):  # readings 1 .. period-1 of the segment
                f = yield u
                if f < best_f:
                    best_u, best_f = np.array(u, dtype=np.float64), float(f)
                if k < period - 1:
                    u = search.send(f)
            self._remeasuring = True
            best_f = yield best_u.copy()  # fresh value: the machine may have moved

    def tell(self, x, y: float) -> None:
        """Report ``y`` at the asked ``x`` (see :class:`~pigp_torch.optimizers.NelderMead`); a
        re-measurement is recorded in :attr:`restarts`."""
        super().tell(x, y)
        if self._remeasuring:
            self._remeasuring = False
            self.restarts.append((self.n_told - 1, self.X[-1].clone(), self.Y[-1]))

    def recommend(self) -> torch.Tensor:
        """``d`` setting of the most recent re-measured best (before the first restart: the best
        reading so far)."""
        if self.restarts:
            return self.restarts[-1][1].clone()
        return self.best()[0]
