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
   warm-started at the previous fit;
2. **asks the model's optimum** of the goal :math:`g(M(x, \hat\theta))` (to minimize, e.g. the mean
   absolute error to a target) inside a trust region: the box of half width :math:`r` (fraction of
   each knob's range) around the best measured setting, clipped to the bounds; multi-start
   L-BFGS-B (:func:`~pigp_torch._utils.multistart.maximize_from`) from the ``n_refine`` best of
   ``n_candidates`` Sobol points, the best setting and the previous ask.

The region grows (:math:`r \to \min(2r, r_{max})`) after a measurement better than the best
before it and shrinks (:math:`r \to \max(r/2, r_{min})`) otherwise.

The scalar ``y`` told with each reading is the objective the caller scores (for :meth:`best`);
the fit uses the observables (``tell(x, y, observables=o)``).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch

from pigp_torch._utils import DTYPE
from pigp_torch._utils.multistart import maximize_from
from pigp_torch.optimizers.base import AskTellOptimizer


def fit_unknowns(
    model: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
    X: torch.Tensor,
    O: torch.Tensor,
    center: torch.Tensor,
    half_width: torch.Tensor,
    *,
    obs_sd: float,
    prior_sd: float,
    u0: torch.Tensor | None = None,
    max_iter: int = 20,
    tol: float = 1e-8,
) -> tuple[torch.Tensor, float]:
    r"""Levenberg–Marquardt fit of the normalized unknowns (module docstring, step 1).

    Args:
        model: ``(N x d knobs, P unknowns) -> N x m`` observables, differentiable in the unknowns.
        X: ``N x d`` settings; O: ``N x m`` observables read there.
        center, half_width: ``P`` each; :math:`\theta = c + h \odot u`.
        obs_sd: observation noise :math:`s` (observable units); prior_sd: :math:`\sigma_u`.
        u0: ``P`` start (default zeros, the prior mean).
        max_iter: LM iterations; tol: stop when the cost changes by less than ``tol`` (relative).

    Returns:
        ``(u, cost)``: the fitted ``P`` normalized unknowns and the cost (the objective above).
    """
    P = center.numel()
    u = torch.zeros(P, dtype=DTYPE) if u0 is None else u0.detach().clone()

    def residual(v: torch.Tensor) -> torch.Tensor:
        pred = model(X, center + half_width * v)
        return torch.cat([((O - pred) / obs_sd).reshape(-1), v / prior_sd])

    r = residual(u).detach()
    cost = float(r @ r)
    lam = 1e-3
    for _ in range(int(max_iter)):
        J = torch.autograd.functional.jacobian(
            residual, u, strategy="forward-mode", vectorize=True
        ).detach()
        A = J.T @ J
        g = J.T @ r
        improved = False
        for _ in range(10):
            step = torch.linalg.solve(A + lam * torch.diag(A.diagonal() + 1e-12), -g)
            r_new = residual(u + step).detach()
            c_new = float(r_new @ r_new)
            if math.isfinite(c_new) and c_new < cost:
                improved = True
                break
            lam *= 10.0
        if not improved:
            break
        rel = (cost - c_new) / max(cost, 1e-300)
        u, r, cost = u + step, r_new, c_new
        lam = max(lam / 10.0, 1e-9)
        if rel < tol:
            break
    return u, cost


class FittedModelOptimizer(AskTellOptimizer):
    r"""Ask the optimum of a model whose unknowns are fitted to the observables (module docstring).

    Args:
        bounds: ``2 x d`` knob bounds.
        model: ``(N x d, P) -> N x m`` differentiable model of the observables.
        goal: ``N x m`` observables ``->`` ``N`` values to minimize (smooth; e.g. a smoothed mean
            absolute error to the target).
        theta_center, theta_half_width: ``P`` centre and half width of the unknowns' ranges.
        obs_sd: observation noise (observable units) in the fit.
        prior_sd: prior width :math:`\sigma_u` in normalized units (default :math:`1/\sqrt3`).
        trust: initial trust-region half width, fraction of each knob's range (default 0.25).
        trust_min, trust_max: its limits (default 0.01, 1).
        n_candidates, n_refine: Sobol candidates and L-BFGS-B starts of the ask (256, 4).
        maxiter: L-BFGS-B iterations of the ask (default 100).
        fit_iter: Levenberg–Marquardt iterations per fit (default 20).
        seed: seed of the Sobol candidates.
        maximize: direction of the told scalar ``y`` (used by :meth:`best` and the trust region).

    Attributes:
        uses_observables: ``True``: ``tell`` takes ``observables``.
        u: the fitted normalized unknowns (``P``); theta: the fitted unknowns.
        fit_cost: the cost of the last fit; trust: the current trust-region half width.
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
        obs_sd: float,
        prior_sd: float = 1 / math.sqrt(3),
        trust: float = 0.25,
        trust_min: float = 0.01,
        trust_max: float = 1.0,
        n_candidates: int = 256,
        n_refine: int = 4,
        maxiter: int = 100,
        fit_iter: int = 20,
        seed: int = 0,
        maximize: bool = False,
    ) -> None:
        super().__init__(bounds, maximize=maximize)
        self.model = model
        self.goal = goal
        self.center = torch.as_tensor(theta_center, dtype=DTYPE).reshape(-1)
        self.half_width = torch.as_tensor(theta_half_width, dtype=DTYPE).reshape(-1)
        if self.center.shape != self.half_width.shape or (self.half_width <= 0).any():
            raise ValueError("theta_center and theta_half_width must be P and half widths > 0")
        if not (obs_sd > 0 and prior_sd > 0):
            raise ValueError("obs_sd and prior_sd must be > 0")
        if not (0 < trust_min <= trust <= trust_max):
            raise ValueError("need 0 < trust_min <= trust <= trust_max")
        self.obs_sd = float(obs_sd)
        self.prior_sd = float(prior_sd)
        self.trust = float(trust)
        self.trust_min = float(trust_min)
        self.trust_max = float(trust_max)
        self.n_candidates = int(n_candidates)
        self.n_refine = int(n_refine)
        self.maxiter = int(maxiter)
        self.fit_iter = int(fit_iter)
        self.seed = int(seed)
        self.O: list[torch.Tensor] = []
        self.u = torch.zeros_like(self.center)
        self.fit_cost = float("nan")
        self._last_ask: torch.Tensor | None = None

    @property
    def theta(self) -> torch.Tensor:
        """The fitted unknowns (``P``, model units)."""
        return self.center + self.half_width * self.u

    def tell(self, x, y: float, observables=None) -> None:
        """Record a reading: knobs ``x`` (``d``), scalar ``y`` and the ``m`` observables; refit."""
        if observables is None:
            raise ValueError(f"{type(self).__name__} needs the observables with each reading")
        best_before = self.best()[1] if self.Y else None
        super().tell(x, y)
        self.O.append(torch.as_tensor(observables, dtype=DTYPE).reshape(-1).clone())
        if best_before is not None:
            better = y > best_before if self.maximize else y < best_before
            self.trust = (
                min(2 * self.trust, self.trust_max)
                if better
                else max(self.trust / 2, self.trust_min)
            )
        self.u, self.fit_cost = fit_unknowns(
            self.model,
            torch.stack(self.X),
            torch.stack(self.O),
            self.center,
            self.half_width,
            obs_sd=self.obs_sd,
            prior_sd=self.prior_sd,
            u0=self.u,
            max_iter=self.fit_iter,
        )

    def predict(self, X: torch.Tensor) -> torch.Tensor:
        """The fitted model's observables at ``N x d`` settings (``N x m``)."""
        with torch.no_grad():
            return self.model(X, self.theta)

    def ask(self) -> torch.Tensor:
        """The fitted model's optimum of the goal inside the trust region (``d``)."""
        if not self.Y:
            raise RuntimeError("tell() the start point first")
        x_best, _ = self.best()
        lo, hi = self.bounds
        half = self.trust * (hi - lo)
        box = torch.stack([torch.maximum(lo, x_best - half), torch.minimum(hi, x_best + half)])
        width = box[1] - box[0]
        sobol = torch.quasirandom.SobolEngine(self.dim, scramble=True, seed=self.seed + self.n_told)
        Z = sobol.draw(self.n_candidates, dtype=DTYPE)
        extra = [x_best] + ([self._last_ask] if self._last_ask is not None else [])
        Ze = ((torch.stack(extra) - box[0]) / width.clamp_min(1e-300)).clamp(0.0, 1.0)
        Z = torch.cat([Ze, Z])
        theta = self.theta.detach()
        with torch.no_grad():
            values = self.goal(self.model(box[0] + width * Z, theta))
        starts = Z[torch.argsort(values)[: self.n_refine]]

        def f(X: torch.Tensor) -> torch.Tensor:
            return -self.goal(self.model(X, theta))

        Xs, ys = maximize_from(f, box, starts, maxiter=self.maxiter)
        x = Xs[int(ys.argmax())].detach()
        x = torch.minimum(torch.maximum(x, lo), hi)
        self._last_ask = x.clone()
        return x
