r"""Tuning through a differentiable machine model whose unknowns are fitted online.

For a machine that returns observables :math:`o \in \mathbb R^m` (e.g. a screen's beam centroid and
size) at knobs :math:`x \in \mathbb R^d`, and a differentiable model :math:`o = M(x, \theta)` whose
parameters :math:`\theta \in \mathbb R^P` the operator does not know (e.g. the incoming beam and
the misalignments), each step

1. **fits the unknowns** to every reading so far by regularized least squares (the posterior mode
   under Gaussian noise and a Gaussian prior), in normalized coordinates
   :math:`\theta = c + h \odot u` (``theta_center`` :math:`c`, ``theta_half_width`` :math:`h`):

   .. math:: \hat u = \arg\min_u \sum_{k} \Big\| \frac{o_k - M(x_k, c + h \odot u)}{s} \Big\|^2
       + \Big\| \frac{u}{\sigma_u} \Big\|^2,

   :math:`s` the observation noise (m), :math:`\sigma_u` the prior width (default
   :math:`1/\sqrt 3`, the standard deviation of a uniform draw on :math:`[-1, 1]`: the unknowns'
   ranges). Solved by Levenberg–Marquardt with the Jacobian of the model by forward-mode autograd,
   warm-started at the previous fit, stopped when the cost drops by less than ``fit_cost_tol``
   (default 1e-3, in squared noise units); a fit that misses the readings by more than 3 noise
   sd on average is repeated from the prior mean and a few draws of the unknowns' ranges, the
   best kept (a warm start can hold the fit in a poor local minimum). Readings at a setting
   read before are merged into their mean counted ``n`` times (the same least squares, fewer
   model rows);
2. **asks the model's optimum** of the goal :math:`g(M(x, \hat\theta))` (to minimize, e.g. the mean
   absolute error to a target) inside a trust region: the box of half width :math:`r` (fraction of
   each knob's range) around the best measured setting, clipped to the bounds. The ``n_refine``
   best of ``n_candidates`` Sobol points (plus the best setting and the previous ask) start a
   batched, box-projected Levenberg–Marquardt on the goal's residuals :math:`\|\rho(M(x,
   \hat\theta))\|^2` when ``residual`` :math:`\rho` is given (e.g. observables minus target: a
   reachable target is a root, found in a few Gauss–Newton steps); the ``n_polish`` best end points
   are then polished by L-BFGS-B on the goal itself (``maxiter`` iterations, stopped at a change
   of ``search_ftol`` noise units; skipped when the best goal is at most ``polish_tol`` noise
   standard deviations), and the best of all end points is asked. When the fit has not
   moved since the last search (the prediction at the previous ask changed by at most
   ``reuse_tol`` noise standard deviations), the previous ask lies in the region, and the region
   has not grown, the previous ask is asked again without a search.

The region grows (:math:`r \to \min(2r, r_{max})`) after a measurement better than the best
before it or one the model predicted (every observable within ``agree_sd`` noise standard
deviations of the prediction of the fit before it), and shrinks (:math:`r \to \max(r/2,
r_{min})`) otherwise: the region guards against a model that does not explain the machine, not
against repeating its optimum.

A :class:`~pigp_torch.prior.machine_model.MachineModel` gives all of the model's parts at once
(:meth:`FittedModelOptimizer.from_machine_model`).

The scalar ``y`` told with each reading is the objective the caller scores; the fit uses the
observables (``tell(x, y, observables=o)``). :meth:`best` is the measured setting with the best
``y`` (``best_from="readings"``) or the measured setting where the fitted model predicts the best
goal (``"model"``: with a noisy screen the luckiest reading is not the best setting).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable

import torch

from pigp_torch._utils import DTYPE
from pigp_torch.optimizers._least_squares import (
    MergedReadings,
    fit_unknowns,
    fit_with_restarts,
    search_in_box,
)
from pigp_torch.optimizers.base import AskTellOptimizer

__all__ = ["FittedModelOptimizer", "ModelFitSettings", "fit_unknowns"]


#: Fixed parts of the method (module docstring): the trust region's limits (fraction of each
#: knob's range), the ask's Sobol candidates and refined starts, the polish's L-BFGS-B iterations
#: and stopping change (noise units), the ask's and the fit's Levenberg–Marquardt iterations,
#: the fit's stopping cost change and restart threshold (squared noise units), the noise sd
#: within which a reading agrees with the model and the fit "has not moved", and the
#: least-squares end points polished.
TRUST_MIN, TRUST_MAX = 0.01, 1.0
N_CANDIDATES, N_REFINE = 256, 16
MAXITER, SEARCH_FTOL = 30, 1e-6
LS_ITER, FIT_ITER = 30, 20
FIT_COST_TOL, RESTART_ABOVE = 1e-3, 9.0
AGREE_SD, REUSE_TOL = 3.0, 0.05
N_POLISH = 2


@dataclasses.dataclass(frozen=True)
class ModelFitSettings:
    r"""The options of a :class:`FittedModelOptimizer`, checked once.

    Args:
        obs_sd: observation noise :math:`s` of the fit (observable units), > 0.
        prior_sd: prior width :math:`\sigma_u` in normalized units (default :math:`1/\sqrt3`).
        trust: initial trust-region half width, fraction of each knob's range, in
            ``[TRUST_MIN, TRUST_MAX]`` (default 0.25).
        fit_restarts: a fit whose cost per observable number exceeds :data:`RESTART_ABOVE`
            squared noise units is repeated from the prior mean and ``fit_restarts - 1`` Sobol
            draws of the unknowns' ranges, the best kept (default 4; 0: never).
        best_from: ``"readings"`` (default) or ``"model"`` (module docstring).
        seed: seed of the Sobol candidates and the fit's restarts (default 0).
        maximize: direction of the told scalar ``y`` (default ``False``: minimized).

    Raises:
        ValueError: a value out of its range (one line naming it).
    """

    obs_sd: float
    prior_sd: float = 1 / math.sqrt(3)
    trust: float = 0.25
    fit_restarts: int = 4
    best_from: str = "readings"
    seed: int = 0
    maximize: bool = False

    def __post_init__(self) -> None:
        if not (float(self.obs_sd) > 0 and float(self.prior_sd) > 0):
            raise ValueError(f"obs_sd and prior_sd must be > 0, got {self.obs_sd}, {self.prior_sd}")
        if not (TRUST_MIN <= float(self.trust) <= TRUST_MAX):
            raise ValueError(f"trust must lie in [{TRUST_MIN}, {TRUST_MAX}], got {self.trust}")
        if int(self.fit_restarts) < 0:
            raise ValueError(f"fit_restarts must be >= 0, got {self.fit_restarts}")
        if self.best_from not in ("readings", "model"):
            raise ValueError(f"best_from must be 'readings' or 'model', got {self.best_from!r}")


class FittedModelOptimizer(AskTellOptimizer):
    r"""Ask the optimum of a model whose unknowns are fitted to the observables (module docstring).

    Args:
        bounds: ``2 x d`` knob bounds.
        model: ``(N x d, P) -> N x m`` differentiable model of the observables.
        goal: ``N x m`` observables ``->`` ``N`` values to minimize (smooth; e.g. a smoothed mean
            absolute error to the target).
        theta_center, theta_half_width: ``P`` centre and half width of the unknowns' ranges.
        residual: ``N x m`` observables ``->`` ``N x r`` residuals whose zero is the goal's
            optimum (e.g. observables minus target; default ``None``: L-BFGS-B on the goal
            only).
        beam: ``(N x m, P) -> N x m``, what the goal and the residual are on, from the predicted
            observables and the ``P`` unknowns (:attr:`~pigp_torch.prior.machine_model.
            MachineModel.beam`: an instrument's response among the unknowns); default ``None``:
            the observables themselves.
        settings: a :class:`ModelFitSettings`, or ``None``: built from ``options``.
        options: :class:`ModelFitSettings` fields (``obs_sd=`` ..., over ``settings``).

    Attributes:
        settings: the :class:`ModelFitSettings` in force (``obs_sd``, ``seed``, ``best_from``
            are also attributes).
        uses_observables: ``True``: ``tell`` takes ``observables``.
        u: the fitted normalized unknowns (``P``); theta: the fitted unknowns.
        fit_cost: the cost of the last fit (all readings); trust: the current trust-region half
            width. n_searches, n_reused: asks that searched / repeated the previous ask.
            n_restarted: fits repeated from other starts (:data:`RESTART_ABOVE`).
        last_misfit: the largest ``|o - prediction| / obs_sd`` of the last reading.
    """

    name = "model-fit"
    uses_observables = True

    def __init__(
        self,
        bounds,
        *,
        model: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
        goal: Callable[[torch.Tensor], torch.Tensor],
        theta_center,
        theta_half_width,
        residual: Callable[[torch.Tensor], torch.Tensor] | None = None,
        beam: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None = None,
        settings: ModelFitSettings | None = None,
        **options,
    ) -> None:
        s = (
            ModelFitSettings(**options)
            if settings is None
            else dataclasses.replace(settings, **options)
        )
        super().__init__(bounds, maximize=s.maximize)
        self.settings = s
        self.model = model
        self.goal = goal
        self.residual = residual
        self.beam = beam
        self.center = torch.as_tensor(theta_center, dtype=DTYPE).reshape(-1)
        self.half_width = torch.as_tensor(theta_half_width, dtype=DTYPE).reshape(-1)
        if self.center.shape != self.half_width.shape or (self.half_width <= 0).any():
            raise ValueError("theta_center and theta_half_width must be P and half widths > 0")
        self.trust = float(s.trust)
        self.n_restarted = 0
        self.last_misfit = float("nan")
        self.n_searches = 0
        self.n_reused = 0
        self._search_theta: torch.Tensor | None = None
        self._fit_theta: torch.Tensor | None = None
        self._best_cache: tuple | None = None
        self._search_trust = 0.0
        self._merged = MergedReadings()
        self.O: list[torch.Tensor] = []
        self.u = torch.zeros_like(self.center)
        self.fit_cost = float("nan")
        self._last_ask: torch.Tensor | None = None
        self.machine_model = None

    @property
    def obs_sd(self) -> float:
        """The observation noise of the fit (observable units)."""
        return float(self.settings.obs_sd)

    @property
    def seed(self) -> int:
        """The seed of the Sobol candidates and the fit's restarts."""
        return int(self.settings.seed)

    @property
    def best_from(self) -> str:
        """How :meth:`best` chooses: ``"readings"`` or ``"model"``."""
        return self.settings.best_from

    @classmethod
    def from_machine_model(
        cls, machine_model, *, obs_sd: float, bounds=None, **options
    ) -> FittedModelOptimizer:
        """The optimizer of a :class:`~pigp_torch.prior.machine_model.MachineModel`: its
        ``observe``, ``goal``, ``residual`` and unknowns' ranges; ``bounds`` default to the
        model's. ``options``: the other keyword arguments of the constructor."""
        opt = cls(
            machine_model.bounds if bounds is None else bounds,
            model=machine_model.observe,
            goal=machine_model.goal,
            residual=machine_model.residual,
            beam=machine_model.beam,
            theta_center=machine_model.unknown_center,
            theta_half_width=machine_model.unknown_half_width,
            obs_sd=obs_sd,
            **options,
        )
        opt.machine_model = machine_model
        return opt

    @property
    def theta(self) -> torch.Tensor:
        """The fitted unknowns (``P``, model units)."""
        return self.center + self.half_width * self.u

    def aim(self, O: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
        """What the goal is on (``N x m``): the predicted observables ``O``, or their beam
        (``beam``) under the first ``P`` of ``theta`` (a tracker's ``theta`` has more)."""
        return O if self.beam is None else self.beam(O, theta[..., : self.center.numel()])

    def goal_at(self, X: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
        """The model's goal at ``N x d`` settings under ``theta`` (``N``, through :meth:`aim`)."""
        return self.goal(self.aim(self.model(X, theta), theta))

    def tell(self, x, y: float, observables=None) -> None:
        """Record a reading: knobs ``x`` (``d``), scalar ``y`` and the ``m`` observables; refit."""
        if observables is None:
            raise ValueError(f"{type(self).__name__} needs the observables with each reading")
        best_before = self.best()[1] if self.Y else None
        o_new = torch.as_tensor(observables, dtype=DTYPE).reshape(-1).clone()
        agree = False
        if self._fit_theta is not None:
            with torch.no_grad():
                pred = self.model(self._check_point(x)[None], self._fit_theta)[0]
            self.last_misfit = float(((o_new - pred).abs() / self.obs_sd).max())
            agree = self.last_misfit <= AGREE_SD
        super().tell(x, y)
        self.O.append(o_new)
        if best_before is not None:
            better = y > best_before if self.maximize else y < best_before
            self.trust = (
                min(2 * self.trust, TRUST_MAX)
                if better or agree
                else max(self.trust / 2, TRUST_MIN)
            )
        # Readings at a setting read before are merged (their mean, counted n times): the same
        # least squares with fewer model rows (the ask repeats its optimum while the fit stands).
        self._merged.add(self.X[-1], self.O[-1])
        self.u, merged_cost = self._fit()
        self.fit_cost = merged_cost + self._merged.scatter(self.O, self.obs_sd)
        self._fit_theta = self.theta.detach().clone()

    def _fit(self) -> tuple[torch.Tensor, float]:
        """The fit of the unknowns to the merged readings (:func:`fit_with_restarts`)."""
        X, O, n = self._merged.arrays()
        u, cost, restarted = fit_with_restarts(
            self.model,
            X,
            O,
            self.center,
            self.half_width,
            obs_sd=self.obs_sd,
            prior_sd=float(self.settings.prior_sd),
            u0=self.u,
            max_iter=FIT_ITER,
            weights=n,
            cost_tol=FIT_COST_TOL,
            restarts=int(self.settings.fit_restarts),
            restart_above=RESTART_ABOVE,
            seed=self.seed + self.n_told,
        )
        self.n_restarted += int(restarted)
        return u, cost

    def best(self) -> tuple[torch.Tensor, float]:
        """The best measured ``(x, y)``: by the readings ``y`` (``best_from="readings"``), or the
        measured setting where the fitted model predicts the best goal (``"model"``; with a noisy
        screen one lucky reading does not decide), with the ``y`` read there."""
        if self.best_from == "readings" or self._fit_theta is None:
            return super().best()
        cache = self._best_cache
        if cache is None or cache[0] != self.n_told or cache[1] is not self._fit_theta:
            with torch.no_grad():
                g = self.goal_at(torch.stack(self.X), self._fit_theta)
            g = torch.where(torch.isfinite(g), g, torch.full_like(g, torch.inf))
            self._best_cache = (self.n_told, self._fit_theta, int(g.argmin()))
        i = self._best_cache[2]
        return self.X[i].clone(), self.Y[i]

    def predict(self, X: torch.Tensor) -> torch.Tensor:
        """The fitted model's observables at ``N x d`` settings (``N x m``)."""
        with torch.no_grad():
            return self.model(X, self.theta)

    def _search_box(self) -> torch.Tensor:
        """``2 x d``: the trust region around the best setting, clipped to the bounds."""
        x_best, _ = self.best()
        lo, hi = self.bounds
        half = self.trust * (hi - lo)
        return torch.stack([torch.maximum(lo, x_best - half), torch.minimum(hi, x_best + half)])

    def _fit_change(self, theta: torch.Tensor) -> float:
        r"""The largest change of the model's prediction at the last ask since the last search,
        in noise standard deviations (``inf`` before the first search)."""
        if self._last_ask is None or self._search_theta is None:
            return float("inf")
        with torch.no_grad():
            x = self._last_ask[None]
            change = self.model(x, theta) - self.model(x, self._search_theta)
        return float(change.abs().max()) / self.obs_sd

    def ask(self) -> torch.Tensor:
        """The fitted model's optimum of the goal inside the trust region (``d``)."""
        if not self.Y:
            raise RuntimeError("tell() the start point first")
        x_best, _ = self.best()
        lo, hi = self.bounds
        box = self._search_box()
        theta = self.theta.detach()
        last = self._last_ask
        inside = last is not None and bool(((last >= box[0]) & (last <= box[1])).all())
        same_region = inside and self.trust <= self._search_trust
        change = self._fit_change(theta) if same_region else float("inf")
        if change <= REUSE_TOL:
            # The fit did not move: the previous optimum is still the model's optimum.
            self.n_reused += 1
            return last.clone()
        width = box[1] - box[0]
        sobol = torch.quasirandom.SobolEngine(self.dim, scramble=True, seed=self.seed + self.n_told)
        Z = sobol.draw(N_CANDIDATES, dtype=DTYPE)
        extra = [x_best] + ([last] if last is not None else [])
        Ze = ((torch.stack(extra) - box[0]) / width.clamp_min(1e-300)).clamp(0.0, 1.0)
        Z = torch.cat([Ze, Z])
        with torch.no_grad():
            values = self.goal_at(box[0] + width * Z, theta)
        values = torch.where(torch.isfinite(values), values, torch.full_like(values, torch.inf))
        order = torch.argsort(values)
        # The N_REFINE best candidates are refined together (one batched evaluation per
        # iteration); the previous ask inside the box is one more start (a warm start).
        starts = Z[order[:N_REFINE]]
        if inside:
            starts = torch.cat([Ze[-1:], starts])

        residual = None
        if self.residual is not None:

            def residual(X: torch.Tensor) -> torch.Tensor:
                return self.residual(self.aim(self.model(X, theta), theta))

        X, v = search_in_box(
            functools.partial(self.goal_at, theta=theta),
            residual,
            box,
            starts,
            scale=self.obs_sd,
            ls_iter=LS_ITER,
            n_polish=N_POLISH,
            polish_tol=0.0,  # always polished
            maxiter=MAXITER,
            ftol=SEARCH_FTOL,
        )
        v = torch.where(torch.isfinite(v), v, torch.full_like(v, torch.inf))
        i = int(v.argmin())
        x = X[i] if bool(v[i] <= values[order[0]]) else box[0] + width * Z[order[0]]
        x = torch.minimum(torch.maximum(x.detach(), lo), hi)
        self._last_ask = x.clone()
        self._search_theta = theta.clone()
        self._search_trust = self.trust
        self.n_searches += 1
        return x
