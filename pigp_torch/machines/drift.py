r"""Processes that change a simulated machine while it is tuned, shared by every machine kind.

A drifting machine's hidden state is a function of the reading count :math:`t = 0, 1, 2, \dots`
(the index of the reading; readings come at a steady rate, so :math:`t` is time in readings):

* :class:`DriftPath`: an offset :math:`\Delta(t) \in \mathbb R^P` added to some hidden
  parameters, the sum of three parts, each optional:

  .. math:: \Delta(t) = v\,t + \sum_{s < t} w_s + J\,[t \ge t_J],

  a linear ramp (rate :math:`v` per reading), a random walk (increments :math:`w_s \sim
  N(0, \mathrm{diag}(q^2))`, drawn once from a seeded generator, so the path is one function of
  :math:`t` whatever the order of the calls) and a step :math:`J` at reading :math:`t_J`.
* :class:`PlayHysteresis`: the acting field of a magnet as the play (backlash) operator of its
  setpoint history, per magnet with half width :math:`w \ge 0`:

  .. math:: y_n = \min\bigl(x_n + w,\ \max(x_n - w,\ y_{n-1})\bigr),

  so the field lags the setpoint by up to :math:`w` and the same setpoint reached from below
  (:math:`y = x - w`) or from above (:math:`y = x + w`) acts differently; :math:`w = 0` is no
  hysteresis. This is the simplest rate-independent hysteresis (a single Prandtl play; a sum of
  plays is the Prandtl–Ishlinskii model of iron-dominated magnets).
* :func:`optimum_track`: the optimum :math:`x^*_t` and :math:`f^*_t = \max_x f_t(x)` of a
  time-dependent objective on a coarse grid of times, each search warm-started from the previous
  optimum (plus Sobol starts at the first), and :math:`f^*_t` linearly interpolated between the
  grid times.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from pigp_torch._utils import DTYPE
from pigp_torch._utils.multistart import find_optimum


@dataclass
class DriftPath:
    r"""An offset :math:`\Delta(t)` of ``P`` hidden parameters against the reading count (module
    docstring).

    Args:
        rate: ``P`` linear rate :math:`v` per reading (default 0).
        walk_sd: ``P`` standard deviation :math:`q` of the random walk's increment per reading
            (default 0: no walk).
        step: ``P`` jump :math:`J` (default 0: no step).
        step_at: reading :math:`t_J` of the step (default ``None``: no step).
        seed: seed of the walk's increments.
        horizon: readings whose increments are drawn at once (more are drawn on demand, in the
            same stream, so :math:`\Delta(t)` does not depend on the horizon but for the rounding of
            the running sums).

    Raises:
        ValueError: parts of different sizes, a negative ``walk_sd`` or ``step_at``.
    """

    rate: Tensor | Sequence[float] | None = None
    walk_sd: Tensor | Sequence[float] | None = None
    step: Tensor | Sequence[float] | None = None
    step_at: int | None = None
    seed: int = 0
    horizon: int = 1024
    _walk: Tensor = field(init=False, repr=False)

    def __post_init__(self) -> None:
        parts = [p for p in (self.rate, self.walk_sd, self.step) if p is not None]
        if not parts:
            raise ValueError("a drift path needs a rate, a walk or a step")
        size = torch.as_tensor(parts[0], dtype=DTYPE).numel()

        def vec(p) -> Tensor:
            v = torch.zeros(size, dtype=DTYPE) if p is None else torch.as_tensor(p, dtype=DTYPE)
            if v.numel() != size:
                raise ValueError(f"drift parts need {size} numbers each, got {v.numel()}")
            return v.reshape(size).clone()

        self.rate, self.walk_sd, self.step = vec(self.rate), vec(self.walk_sd), vec(self.step)
        if bool((self.walk_sd < 0).any()):
            raise ValueError("walk_sd must be >= 0")
        if self.step_at is not None and int(self.step_at) < 0:
            raise ValueError(f"step_at must be >= 0, got {self.step_at}")
        self._gen = torch.Generator().manual_seed(int(self.seed))
        self._walk = torch.zeros(1, size, dtype=DTYPE)  # cumulative sums, row t = sum_{s<t} w_s
        self._extend(int(self.horizon))

    @property
    def size(self) -> int:
        """``P``, the number of parameters the path moves."""
        return int(self.rate.numel())

    def _extend(self, t: int) -> None:
        have = self._walk.shape[0] - 1
        if t <= have:
            return
        n = max(t - have, 256)
        w = torch.randn(n, self.size, generator=self._gen, dtype=DTYPE) * self.walk_sd
        self._walk = torch.cat([self._walk, self._walk[-1] + torch.cumsum(w, 0)])

    def __call__(self, t: int) -> Tensor:
        r"""``P`` offset :math:`\Delta(t)` at reading ``t`` (``t >= 0``)."""
        t = int(t)
        if t < 0:
            raise ValueError(f"reading index must be >= 0, got {t}")
        self._extend(t)
        out = self.rate * t + self._walk[t]
        if self.step_at is not None and t >= int(self.step_at):
            out = out + self.step
        return out


class PlayHysteresis:
    r"""Acting fields of ``d`` magnets as play operators of their setpoints (module docstring).

    Args:
        width: ``d`` play half widths :math:`w \ge 0` (the knobs' units).
        y0: ``d`` acting fields before the first setpoint (the state the history left).

    Raises:
        ValueError: a negative width, or ``y0`` of another size.
    """

    def __init__(self, width, y0) -> None:
        self.width = torch.as_tensor(width, dtype=DTYPE).reshape(-1).clone()
        if bool((self.width < 0).any()):
            raise ValueError("hysteresis widths must be >= 0")
        self.y = torch.as_tensor(y0, dtype=DTYPE).reshape(-1).clone()
        if self.y.numel() != self.width.numel():
            raise ValueError(f"y0 needs {self.width.numel()} numbers, got {self.y.numel()}")

    def acting(self, x) -> Tensor:
        r"""The acting fields if setpoints ``x`` (``d`` or ``N x d``) were applied now, from the
        present state (does not change it): :math:`\min(x + w, \max(x - w, y))`."""
        x = torch.as_tensor(x, dtype=DTYPE)
        return torch.minimum(x + self.width, torch.maximum(x - self.width, self.y))

    def apply(self, x) -> Tensor:
        """Apply the setpoints ``x`` (``d``): the new state, returned."""
        self.y = self.acting(torch.as_tensor(x, dtype=DTYPE).reshape(-1))
        return self.y.clone()


def optimum_track(
    f_at: Callable[[int], Callable[[Tensor], Tensor]],
    bounds: Tensor,
    times: Sequence[int],
    *,
    n_starts: int = 8,
    seed: int = 0,
    x_start: Tensor | None = None,
) -> tuple[np.ndarray, Tensor, np.ndarray]:
    r"""The optimum of a time-dependent objective on a grid of times.

    Args:
        f_at: ``t -> f_t``, a differentiable ``N x d -> N`` objective (maximized) at reading ``t``.
        bounds: ``2 x d`` knob bounds.
        times: increasing reading indices of the grid.
        n_starts: Sobol starts of the first search (later ones start from the previous optimum
            and from ``x_start``).
        seed: seed of the Sobol starts.
        x_start: ``d`` extra start of every search (e.g. the run's start setting).

    Returns:
        ``(times, X, F)``: the grid (``G`` int array), ``G x d`` optima and ``G`` optimal values.
    """
    times = np.asarray(sorted(int(t) for t in times), dtype=int)
    X, F, prev = [], [], None
    extra = [] if x_start is None else [torch.as_tensor(x_start, dtype=DTYPE).reshape(1, -1)]
    for k, t in enumerate(times):
        starts = extra + ([] if prev is None else [prev.reshape(1, -1)])
        x_init = torch.cat(starts) if starts else None
        x, v = find_optimum(
            f_at(int(t)), bounds, n_starts=n_starts if k == 0 else 0, seed=seed, x_init=x_init
        )
        prev = x
        X.append(x)
        F.append(float(v))
    return times, torch.stack(X), np.asarray(F)


def interpolate_track(times: np.ndarray, values: np.ndarray, t) -> np.ndarray:
    """Linear interpolation of a grid's ``values`` at readings ``t`` (held constant past the
    grid's ends)."""
    return np.interp(np.asarray(t, dtype=float), times.astype(float), values)


def drive(machine, optimizer, readings: int, *, set_back: bool = True):
    r"""Run an ask/tell ``optimizer`` (an :class:`~pigp_torch.optimizers.AskTellOptimizer`:
    ``ask``, ``tell``, the declared ``uses_observables`` and ``recommend``) on ``machine`` for
    ``readings`` readings: reading 0 at the start setting, reading :math:`t \ge 1` at the
    optimizer's ``t``-th ask; each reading is told (with the observables when the optimizer fits
    them, ``uses_observables``). With ``set_back`` the knobs then go to the optimizer's
    recommended setting (``recommend()``, where the optimizer puts the optimum now; by default
    ``best()``'s setting) and one more
    reading is taken.

    Returns:
        ``(X, true)``: ``T x d`` settings of the readings and ``T x m`` true observables
        (``machine.last_true_observables`` after each reading), ``T = readings (+ 1)``.

    Raises:
        ValueError: ``readings < 1``.
    """
    if int(readings) < 1:
        raise ValueError(f"readings must be >= 1, got {readings}")
    X, true = [], []
    fits = bool(optimizer.uses_observables)
    for t in range(int(readings)):
        if t > 0:
            machine.set(optimizer.ask())
        X.append(machine.get())
        y = machine.read()
        optimizer.tell(X[-1], y, **({"observables": machine.last_observables} if fits else {}))
        true.append(machine.last_true_observables.clone())
    if set_back:
        machine.set(optimizer.recommend())
        machine.read()
        X.append(machine.get())
        true.append(machine.last_true_observables.clone())
    return torch.stack(X), torch.stack(true)


def family_components(families: dict[str, frozenset[str]], family: str, what: str):
    """The components of ``family`` in ``families`` (a kind's families, ``what`` names them).

    Raises:
        ValueError: an unknown family (one line naming the known ones).
    """
    if family not in families:
        raise ValueError(f"unknown {what} family {family!r}; known: {list(families)}")
    return families[family]


def window_statistic(values, window: tuple[int, int], how: str = "median") -> float:
    r"""The median (or ``how="mean"``) of ``values[t]`` over readings ``window[0] <= t <
    window[1]`` (readings counted from 0, the start).

    Raises:
        ValueError: an empty window or an unknown ``how``.
    """
    v = np.asarray(values, dtype=float)[int(window[0]) : int(window[1])]
    if v.size == 0:
        raise ValueError(f"no readings in window {window} of {len(values)}")
    if how == "median":
        return float(np.median(v))
    if how == "mean":
        return float(np.mean(v))
    raise ValueError(f"how must be 'median' or 'mean', got {how!r}")
