r"""One ask/tell Bayesian optimizer composed of a posterior, an acquisition, a search and a region.

:class:`BayesianOptimizer` runs the same steps for every method:

* ``tell(x, y)``: record the reading and pass it to the posterior (``observe``; an incremental
  posterior updates there);
* ``ask()``: fit the posterior to all readings (internal, maximized sign; the prior check of the
  physics posterior runs here and its notices go to :attr:`notices`), choose the region's centre
  and box, bind the acquisition to the posterior, maximize it with the search from the centre
  and the posterior's extra starts, and clamp the result into the box.

The parts (:class:`BOParts`) are small protocols with several implementations each:

* posterior (:class:`~pigp_torch.models.posterior.Posterior`): BoTorch model, incremental exact
  GP, online-fitted physics form with residual GP;
* acquisition (:mod:`~pigp_torch.optimizers.bo.acquisition`): ``bind(posterior, best_f, step)``
  returns what the search maximizes (a ``fun(X, order)`` with a ``max_order`` attribute, 1 when
  absent, or a BoTorch acquisition object);
* search (:mod:`~pigp_torch.optimizers.bo.search`): ``maximize(objective, box, starts, seed,
  max_order) -> (x, value, info)``;
* region (:class:`~pigp_torch.optimizers.bo.region.TrustRegion`): ``center(X, Y, posterior)``
  and ``box(center, last)``.

**Determinism.** Each ask hands ``seed + n_told`` to the search; when the posterior or the
search draws from torch's global RNG (``uses_torch_rng``, as BoTorch's model fits and
``optimize_acqf`` do), the ask runs in a forked RNG seeded with the same number. The global RNG
state is left untouched.

After each ask, ``last_info`` holds ``acq_value``, ``center`` (``d``), ``trust_lower`` and
``trust_upper`` (``d``), ``fit_time_s`` (posterior update at the last tell and fit at this ask),
``acq_time_s``, ``n_train``, and what the search and the posterior add.
"""

from __future__ import annotations

import contextlib
import time
from dataclasses import dataclass
from typing import Any, Protocol

import torch

from pigp_torch._utils import DTYPE
from pigp_torch.models.posterior import Posterior
from pigp_torch.optimizers.base import AskTellOptimizer
from pigp_torch.optimizers.bo.region import clamp_to_box


class Acquisition(Protocol):
    """Binds to a fitted posterior: ``bind(posterior, best_f, step)`` returns the search's
    objective (``fun(X: N x d, order)`` in NumPy, or a BoTorch acquisition object)."""

    def bind(self, posterior: Posterior, best_f: Any, step: int) -> Any: ...


class Search(Protocol):
    """Maximizes a bound acquisition in a ``2 x d`` box: ``(x: d, value, info)``."""

    def maximize(
        self, objective: Any, box: torch.Tensor, starts: list, seed: int, max_order: int
    ) -> tuple[torch.Tensor, float, dict]: ...


class Region(Protocol):
    """Chooses the centre among the told points and the box of the next setting; its trust
    box has half-width ``step_limit`` around a centre."""

    step_limit: float | None

    def trust_box(self, center: torch.Tensor) -> torch.Tensor: ...

    def center(self, X: torch.Tensor, Y: torch.Tensor, posterior: Posterior) -> torch.Tensor: ...

    def box(self, center: torch.Tensor, last: torch.Tensor) -> torch.Tensor: ...


@dataclass
class BOParts:
    """The four parts of a :class:`BayesianOptimizer`."""

    posterior: Posterior
    acquisition: Acquisition
    search: Search
    region: Region


class BayesianOptimizer(AskTellOptimizer):
    r"""Ask/tell Bayesian optimization from parts (see the module docstring).

    Args:
        bounds: ``2 x d`` knob bounds.
        parts: the posterior, acquisition, search and region.
        maximize: maximize (default) or minimize; the parts always see the maximized sign
            (:math:`-y` when minimizing).
        seed: base seed of the per-ask RNG.
    """

    name = "bayesian-optimizer"

    def __init__(self, bounds, parts: BOParts, *, maximize: bool = True, seed: int = 0) -> None:
        super().__init__(bounds, maximize=maximize)
        self.parts = parts
        self.sign = 1.0 if self.maximize else -1.0
        self.seed = int(seed)
        self.last_info: dict = {}
        self._tell_time = 0.0

    @property
    def step_limit(self) -> float | None:
        """The region's trust-box half-width (a fraction of each knob's half-range)."""
        return self.parts.region.step_limit

    def trust_box(self, center: torch.Tensor) -> torch.Tensor:
        """The region's ``2 x d`` trust box around ``center`` (``d``)."""
        return self.parts.region.trust_box(center)

    def tell(self, x, y: float) -> None:
        """Record one measurement and pass it to the posterior."""
        super().tell(x, y)
        t0 = time.perf_counter()
        try:
            self.parts.posterior.observe(self.X[-1], self.sign * self.Y[-1])
        except Exception:  # keep the history and the posterior consistent
            self.X.pop()
            self.Y.pop()
            raise
        self._tell_time = time.perf_counter() - t0

    def train_data(self) -> tuple[torch.Tensor, torch.Tensor]:
        """All told data as ``(X: n x d, Y: n)``, ``Y`` negated when minimizing."""
        if not self.Y:
            raise RuntimeError("no measurements yet: tell() the start point first")
        return torch.stack(self.X), self.sign * torch.tensor(self.Y, dtype=DTYPE)

    def ask(self) -> torch.Tensor:
        """Fit, choose the box, maximize the acquisition in it; returns ``d``."""
        X, Y = self.train_data()
        p = self.parts
        step = self.n_told
        forks = any(getattr(part, "uses_torch_rng", False) for part in (p.posterior, p.search))
        with torch.random.fork_rng() if forks else contextlib.nullcontext():
            if forks:
                torch.manual_seed(self.seed + step)
            t0 = time.perf_counter()
            p.posterior.fit(X, Y)
            for notice in p.posterior.take_notices():
                self.notify(**notice)
            t1 = time.perf_counter()
            center = p.region.center(X, Y, p.posterior)
            box = p.region.box(center, X[-1])
            objective = p.acquisition.bind(p.posterior, Y.max(), step)
            starts = [center, *p.posterior.extra_starts(box)]
            order = min(p.posterior.max_order, getattr(objective, "max_order", 1))
            x, value, info = p.search.maximize(objective, box, starts, self.seed + step, order)
            t2 = time.perf_counter()
        x = clamp_to_box(x, box)  # final guard against round-off
        self.last_info = {
            "acq_value": float(value),
            "center": center.clone(),
            "trust_lower": box[0].clone(),
            "trust_upper": box[1].clone(),
            "fit_time_s": self._tell_time + t1 - t0,
            "acq_time_s": t2 - t1,
            "n_train": X.shape[0],
            **info,
            **p.posterior.info(),
        }
        return x
