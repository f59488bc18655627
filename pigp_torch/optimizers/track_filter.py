r"""A state-space fit of a model's unknowns that follows them in time.

:class:`UnknownsFilter` tracks the normalized unknowns :math:`u_t` (:math:`\theta = c + h \odot
u`) of a differentiable model :math:`o = M(x, \theta) + v`, :math:`v \sim N(0, s^2 I)`, in
information form. Each reading :math:`(x_t, o_t)` (time :math:`t`: the readings told)

1. **forgets**: the readings' information :math:`\Lambda` and linear term :math:`\eta` decay,
   :math:`\Lambda^- = \lambda\Lambda`, :math:`\eta^- = \lambda\eta` (exponentially weighted least
   squares: a reading of age :math:`a` counts :math:`\lambda^a`), while the prior
   :math:`H_0 = I / \sigma_u^2` at the prior mean stays; the prediction is the posterior mean
   :math:`u^- = (\Lambda^- + H_0)^{-1}\eta^-` (directions no recent reading determines return to
   the prior instead of wandering; :math:`\lambda = 1` keeps every reading: the batch fit);
2. **scores** the prediction: innovation :math:`\nu = o_t - M(x_t, \theta(u^-))`, covariance
   :math:`S = J (\Lambda^- + H_0)^{-1} J^\top + s^2 I` (:math:`J = \partial M / \partial u` at the
   reading), score :math:`\sum_t \gamma^{n-t} \log N(\nu_t; 0, S_t)`;
3. **updates** by a few Gauss–Newton steps on the new reading (an iterated extended information
   filter): linearized at :math:`u`, :math:`\Lambda = \Lambda^- + J^\top J / s^2`,
   :math:`\eta = \eta^- + J^\top (o_t - M(x_t, \theta(u)) + J u) / s^2`,
   :math:`u \leftarrow (\Lambda + H_0)^{-1} \eta`.

4. **relinearizes** now and then (:meth:`UnknownsFilter.refit`): the information of the past
   readings was taken at the estimates of their time, which a nonlinear model then mispredicts;
   a refit replaces each filter's state by the weighted batch fit of every reading so far
   (Levenberg–Marquardt warm-started at the estimate, reading :math:`t` weighted
   :math:`\lambda^{n-t}` times the caller's weights), with the information at that fit,
   :math:`\Lambda = \sum_t \lambda^{n-t} J_t^\top J_t / s^2`, :math:`\eta = (\Lambda + H_0) u`.

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
from pigp_torch.optimizers._least_squares import fit_unknowns, row_jacobian

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
        H: ``P x P`` its information, the prior's included (:func:`information`; default the
            prior's: no reading yet).
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
        self.L = [H - self.H0 for _ in self.forgets]  # the readings' information
        self.eta = [H @ u0.detach() for _ in self.forgets]
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
            L, eta = lam * self.L[g], lam * self.eta[g]
            A = L + self.H0
            u = torch.linalg.solve(A, eta)
            pred, J = self._jacobian(x, u)
            nu = o - pred
            S = J @ torch.linalg.solve(A, J.T) + s2 * torch.eye(len(o), dtype=DTYPE)
            _, logdet = torch.linalg.slogdet(2 * math.pi * S)
            loglik = -0.5 * (nu @ torch.linalg.solve(S, nu) + logdet)
            self.scores[g] = self.discount * self.scores[g] + loglik
            if g == chosen:
                self.last_z = nu / torch.diagonal(S).sqrt()
            for it in range(self.iters):
                if it:
                    pred, J = self._jacobian(x, u)
                L_new = L + J.T @ J / s2
                eta_new = eta + J.T @ (o - pred + J @ u) / s2
                u = torch.linalg.solve(L_new + self.H0, eta_new)
            self.U[g], self.L[g], self.eta[g] = u, L_new, eta_new
        self.chosen = int(self.scores.argmax())

    def refit(self, X, O, weights=None, *, max_iter: int = 5) -> None:
        r"""Relinearize every filter at its weighted batch fit of all readings (module docstring,
        step 4): ``X`` (``n x d``) and ``O`` (``n x m``) the readings in order, ``weights``
        (``n``, default ones) multiplied by :math:`\lambda^{n-t}`; readings weighted under
        1e-6 are left out; ``max_iter`` Levenberg–Marquardt iterations."""
        X, O = torch.as_tensor(X, dtype=DTYPE), torch.as_tensor(O, dtype=DTYPE)
        n = X.shape[0]
        age = torch.arange(n - 1, -1, -1, dtype=DTYPE)
        base = torch.ones(n, dtype=DTYPE)
        if weights is not None:
            base = torch.as_tensor(weights, dtype=DTYPE)
        for g, lam in enumerate(self.forgets):
            w = base * lam**age
            keep = w > 1e-6
            u, _ = fit_unknowns(self.model, X[keep], O[keep], self.center, self.half_width,
                                obs_sd=self.obs_sd, prior_sd=self.prior_sd, u0=self.U[g],
                                max_iter=max_iter, weights=w[keep])  # fmt: skip
            theta = self.center + self.half_width * u
            J = row_jacobian(self.model, X[keep], theta) * self.half_width  # N x m x P
            J = (J * w[keep].sqrt()[:, None, None]).reshape(-1, J.shape[-1])
            L = J.T @ J / self.obs_sd**2
            self.U[g], self.L[g], self.eta[g] = u, L, (L + self.H0) @ u
