r"""A state-space fit of a model's unknowns that follows them in time.

:class:`UnknownsFilter` tracks the normalized unknowns :math:`u_t` (:math:`\theta = c + h \odot
u`) of a differentiable model :math:`o = M(x, \theta) + v`, :math:`v \sim N(0, s^2 I)`, in
information form. Each reading :math:`(x_t, o_t)` (time :math:`t`: the readings told)

1. **predicts** by forgetting: the information about the unknowns decays towards the prior's,
   :math:`H^- = \lambda (H - H_0) + H_0`, :math:`H_0 = I / \sigma_u^2` (a random walk of the
   unknowns whose size is set by :math:`\lambda`; directions no reading determines keep the
   prior's width, and :math:`\lambda = 1` keeps every reading: the batch fit);
2. **scores** the prediction: innovation :math:`\nu = o_t - M(x_t, \theta(u))`, covariance
   :math:`S = J (H^-)^{-1} J^\top + s^2 I` (:math:`J = \partial M / \partial u` at the reading),
   score :math:`\sum_t \gamma^{n-t} \log N(\nu_t; 0, S_t)`;
3. **updates** by a few Gauss–Newton steps (an iterated extended Kalman filter) on
   :math:`(u - u^-)^\top H^- (u - u^-) + \|(o_t - M(x_t, \theta(u)))/s\|^2`, then
   :math:`H = H^- + J^\top J / s^2`.

One filter runs per forgetting factor of a small grid (default 1, 0.99, 0.95, 0.9); the estimate
used is the filter's with the largest score: the forgetting rate is learned from the one-step-ahead
predictive likelihood (on a static machine the filter that forgets nothing predicts best). For a
linear model the update is exact: with :math:`\lambda = 1` the estimate equals the batch
posterior mean of every reading so far.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch

from pigp_torch._utils import DTYPE
from pigp_torch.optimizers._least_squares import row_jacobian

__all__ = ["FORGET_GRID", "UnknownsFilter", "information"]

#: Forgetting factors per reading of the filters.
FORGET_GRID: tuple[float, ...] = (1.0, 0.99, 0.95, 0.9)


def information(model, X, center, half_width, u, *, obs_sd: float, prior_sd: float):
    r"""``P x P``: :math:`H = \sum_k J_k^\top J_k / s^2 + I / \sigma_u^2` of readings at ``X``
    (``N x d``) around ``u`` (the Gauss–Newton Hessian of the fit, normalized units)."""
    J = row_jacobian(model, X, center + half_width * u) * half_width  # N x m x P
    J = J.reshape(-1, J.shape[-1])
    P = center.numel()
    return J.T @ J / obs_sd**2 + torch.eye(P, dtype=DTYPE) / prior_sd**2


class UnknownsFilter:
    r"""Filters of the unknowns with forgetting (module docstring).

    Args:
        model: ``(N x d, P) -> N x m`` differentiable model.
        center, half_width: ``P`` each: :math:`\theta = c + h \odot u`.
        u0: ``P`` start estimate (normalized; e.g. the batch fit).
        H: ``P x P`` its information (:func:`information`; default the prior's).
        obs_sd: :math:`s` (observable units); prior_sd: :math:`\sigma_u` (normalized units).
        forgets: the grid of :math:`\lambda` (default :data:`FORGET_GRID`).
        discount: :math:`\gamma` of the score (default 0.97).
        iters: Gauss–Newton steps per update (default 3).

    Attributes:
        chosen: index of the filter used; scores: ``G`` scores; last_z: the standardized
            innovations (``m``) of the filter used, before the last update.
    """

    def __init__(
        self,
        model: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
        center: torch.Tensor,
        half_width: torch.Tensor,
        u0: torch.Tensor,
        *,
        obs_sd: float,
        prior_sd: float,
        H: torch.Tensor | None = None,
        forgets=FORGET_GRID,
        discount: float = 0.97,
        iters: int = 3,
    ) -> None:
        self.forgets = tuple(float(f) for f in forgets)
        if not self.forgets or not all(0 < f <= 1 for f in self.forgets):
            raise ValueError(f"forgetting factors must lie in (0, 1], got {forgets}")
        if not (obs_sd > 0 and prior_sd > 0 and 0 < discount <= 1 and iters >= 1):
            raise ValueError("need obs_sd > 0, prior_sd > 0, 0 < discount <= 1, iters >= 1")
        self.model, self.center, self.half_width = model, center, half_width
        self.obs_sd, self.prior_sd = float(obs_sd), float(prior_sd)
        P = center.numel()
        self.H0 = torch.eye(P, dtype=DTYPE) / self.prior_sd**2
        H = self.H0.clone() if H is None else torch.as_tensor(H, dtype=DTYPE)
        self.U = [u0.detach().clone() for _ in self.forgets]
        self.H = [H.clone() for _ in self.forgets]
        self.scores = torch.zeros(len(self.forgets), dtype=DTYPE)
        self.discount, self.iters = float(discount), int(iters)
        self.chosen = 0
        self.last_z = torch.zeros(0, dtype=DTYPE)

    @property
    def u(self) -> torch.Tensor:
        """The estimate used (``P``, normalized)."""
        return self.U[self.chosen]

    @property
    def forget(self) -> float:
        """The forgetting factor learned (the filter used)."""
        return self.forgets[self.chosen]

    def _jacobian(self, x: torch.Tensor, u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        theta = self.center + self.half_width * u
        with torch.no_grad():
            pred = self.model(x[None], theta)[0]
        J = row_jacobian(self.model, x[None], theta)[0] * self.half_width  # m x P
        return pred, J

    def update(self, x, o) -> None:
        """Filter one reading: setting ``x`` (``d``), observables ``o`` (``m``)."""
        x = torch.as_tensor(x, dtype=DTYPE).reshape(-1)
        o = torch.as_tensor(o, dtype=DTYPE).reshape(-1)
        s2 = self.obs_sd**2
        chosen = self.chosen
        for g, lam in enumerate(self.forgets):
            H_pred = lam * (self.H[g] - self.H0) + self.H0
            u_pred = self.U[g]
            pred, J = self._jacobian(x, u_pred)
            nu = o - pred
            S = J @ torch.linalg.solve(H_pred, J.T) + s2 * torch.eye(len(o), dtype=DTYPE)
            _, logdet = torch.linalg.slogdet(2 * math.pi * S)
            loglik = -0.5 * (nu @ torch.linalg.solve(S, nu) + logdet)
            self.scores[g] = self.discount * self.scores[g] + loglik
            if g == chosen:
                self.last_z = nu / torch.diagonal(S).sqrt()
            u = u_pred
            for it in range(self.iters):
                if it:
                    pred, J = self._jacobian(x, u)
                A = H_pred + J.T @ J / s2
                b = J.T @ (o - pred) / s2 - H_pred @ (u - u_pred)
                u = u + torch.linalg.solve(A, b)
            self.U[g], self.H[g] = u, A
        self.chosen = int(self.scores.argmax())
