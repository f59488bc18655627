r"""The fit terms of :class:`~pigp_torch.models.InverseSqrtPeakModel`: the negative log posterior
(torch, and in NumPy with its closed-form gradient for L-BFGS-B), the weighted linear start, the
Laplace covariance and the Laplace evidence (a mixin of the model, in its own module to keep
each file short)."""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from pigp_torch._utils import DTYPE


class FitTerms:
    """The readings' covariance in the fit, negative log posterior, linear start, Laplace
    covariance and evidence of the form."""

    def noise_variances(self, n: int) -> Tensor:
        r"""``n`` noise variances of the readings in the fit: :math:`\sigma_n^2 / w_i` with the
        readings' weights :math:`w_i \in (0, 1]` (``weights``, set by :meth:`fit`; a forgotten
        reading is a noisier one), :math:`\sigma_n^2` each without weights."""
        var = torch.full((n,), self.noise**2, dtype=DTYPE)
        return var if self.weights is None else var / self.weights

    def fit_covariance(self, X: Tensor) -> tuple[Tensor | None, float]:
        r"""``(P, log det Sigma)`` of the readings at ``X`` (``n x d``) in the fit:
        :math:`P = \Sigma^{-1}` (``n x n``) with :math:`\Sigma = K + \sigma_n^2 I` when ``gls``
        (:math:`K` the residual kernel with the precision of the current :math:`\theta`, else
        of :math:`\theta_0`), or ``None`` for :math:`\Sigma = \sigma_n^2 I`. The last
        :meth:`fit`'s own when ``X`` is its data (the same tensor)."""
        n = X.shape[0]
        if not self.gls:
            if self.weights is None:
                return None, 2.0 * n * math.log(self.noise)
            return None, float(torch.log(self.noise_variances(n)).sum())
        if self._fit_cov is not None and self._fit_cov[0] is X:
            return self._fit_cov[1], self._fit_cov[2]
        theta = self.theta
        if theta is None or theta.shape[0] != self.n_params:
            theta = self.prior_theta()
        K = self._k_res(X, X, self.residual_precision(theta))
        L = torch.linalg.cholesky(K + torch.diag(self.noise_variances(n)))
        P = torch.cholesky_inverse(L)
        return (P + P.T) / 2, 2.0 * float(torch.log(L.diagonal()).sum())

    def _neg_log_post(self, theta: Tensor, X: Tensor, Y: Tensor) -> Tensor:
        d = self.dim
        P, _ = self.fit_covariance(X)
        if P is None:
            data = ((Y - self.form(X, theta)) / self.noise) ** 2
            data = (data if self.weights is None else data * self.weights).sum()
        else:
            e = Y - self.form(X, theta)
            data = e @ P @ e
        dmu = theta[:d] - self.center0
        if self.center_cov is None:
            pen = ((dmu / self.tau) ** 2).sum()
        else:
            pen = dmu @ self.center_precision @ dmu
        pen = pen + ((theta[d] - self.log_c_model) / self.log_c_std) ** 2
        pen = pen + (theta[d + 1] / self.log_beta_std) ** 2
        if self.f_inf_std > 0:
            pen = pen + (theta[d + 2] / self.f_inf_std) ** 2
        if self.shape_std > 0:
            pen = pen + (theta[self._s_index :] ** 2).sum() / self.shape_std**2
        return 0.5 * data + 0.5 * pen

    def _linear_start(self, X: Tensor, Y: Tensor) -> Tensor | None:
        r"""Weighted least squares of :math:`g_i - \mathbf x_i^\top B\mathbf x_i = a +
        \mathbf w^\top\mathbf x_i` (:math:`\beta=1`); weights from the delta method,
        :math:`\sigma_{g} = 2\sigma_n (y - f_\infty)^{-3}`."""
        n, d = X.shape
        if n < d + 2:
            return None
        e = (Y - self.f_inf).clamp_min(self.noise)
        w = e**3 if self.weights is None else e**3 * self.weights.sqrt()
        A = torch.cat([torch.ones(n, 1, dtype=DTYPE), X], 1) * w[:, None]
        rhs = (e**-2 - ((X @ self.B) * X).sum(-1)) * w
        # NumPy's LAPACK (gelsd), not torch.linalg.lstsq: torch's CPU solver (MKL gelsy) gives
        # results that differ in the last bits from call to call on the same input (it depends
        # on where the arrays sit in memory), and this start decides between fits, so runs
        # would not repeat.
        sol = torch.from_numpy(np.linalg.lstsq(A.numpy(), rhs.numpy(), rcond=None)[0])
        mu = torch.linalg.solve(self.B, -sol[1:] / 2)
        c = float(sol[0] - mu @ self.B @ mu)
        if not (math.isfinite(c) and torch.isfinite(mu).all()):
            return None
        reach = 3.0 * self.tau
        mu = torch.maximum(torch.minimum(mu, self.center0 + reach), self.center0 - reach)
        log_c = math.log(min(max(c, 1e-3), 1e4))
        tail = [log_c, 0.0] + [0.0] * (self.n_params - d - 2)
        return torch.cat([mu, torch.tensor(tail, dtype=DTYPE)])

    def log_evidence(self) -> float:
        r"""Laplace estimate of the log marginal likelihood of the last :meth:`fit`'s data
        under this model (the residual GP enters through :math:`\Sigma` with ``gls``):

        .. math::
            \log Z \approx -\tfrac12\mathbf r^\top\Sigma^{-1}\mathbf r
            - \tfrac12\,\mathrm{pen}(\hat\theta) - \tfrac n2 \log 2\pi
            - \tfrac12\log\det\Sigma + \tfrac12\log\det\Lambda_0 - \tfrac12\log\det A,

        :math:`\Sigma` the readings' covariance of the fit (:math:`\sigma_n^2 I` without
        ``gls``), :math:`\Lambda_0` the prior precision of :math:`\theta`, :math:`A =
        J^\top\Sigma^{-1}J + \Lambda_0` (Gauss-Newton). Two models of the same readings
        compare by it (a difference of 3 is odds of 20 to 1)."""
        if self.theta is None:
            raise RuntimeError("fit() the model first")
        n = self._n
        return (
            -self.neg_log_post
            - (
                0.5 * n * math.log(2 * math.pi * self.noise**2)
                if self._log_det_noise is None
                else 0.5 * n * math.log(2 * math.pi) + 0.5 * self._log_det_noise
            )
            + 0.5 * self._log_det_prior
            - 0.5 * self._log_det_A
        )

    def prior_precision(self) -> Tensor:
        r"""``n_params x n_params`` prior precision :math:`\Lambda_0` of :math:`\theta` (the
        centre block :math:`C_\mu^{-1}`, then :math:`s_c^{-2}`, :math:`s_\beta^{-2}`[,
        :math:`s_f^{-2}`][, :math:`s_B^{-2}` each])."""
        tail = [self.log_c_std**-2, self.log_beta_std**-2]
        if self.f_inf_std > 0:
            tail.append(self.f_inf_std**-2)
        if self.shape_std > 0:
            tail += [self.shape_std**-2] * self.dim
        tail = torch.diag(torch.tensor(tail, dtype=DTYPE))
        if self.center_cov is None:  # the box prior: diagonal, as before the ensemble option
            return torch.diag(torch.cat([self.tau**-2, tail.diagonal()]))
        return torch.block_diag(self.center_precision, tail)

    def _laplace(self, X: Tensor) -> None:
        J = self.jacobian(X)
        P, log_det = self.fit_covariance(X)
        weighted = P is not None or self.weights is not None
        self._log_det_noise = log_det if weighted else None  # None: n log noise^2
        prior_prec = self.prior_precision()
        if P is None:
            Jw = J if self.weights is None else J * self.weights.unsqueeze(-1)
            A = Jw.T @ J / self.noise**2
        else:
            A = J.T @ P @ J
        A = A + prior_prec
        L = torch.linalg.cholesky(A)
        cov = torch.cholesky_inverse(L)
        self._log_det_A = 2.0 * float(torch.log(L.diagonal()).sum())
        self._log_det_prior = float(torch.linalg.slogdet(prior_prec)[1])
        self.cov = (cov + cov.T) / 2


class _NumpyObjective:
    r"""The negative log posterior :meth:`InverseSqrtPeakModel._neg_log_post` and its gradient
    in closed form, in NumPy, for the L-BFGS-B fit:
    :math:`\nabla = -J^\top \mathbf w + \tfrac12 \nabla\text{pen}`, :math:`J` as in
    :meth:`InverseSqrtPeakModel.jacobian` and :math:`\mathbf w = \Sigma^{-1}(\mathbf y - f)`
    (:math:`(\mathbf y - f)/\sigma_n^2` without ``gls``).

    The arrays have 13-100 entries: at these sizes each torch call costs more
    than its arithmetic, and the fit evaluates it hundreds of times an ask.
    A test checks it against the torch version to round-off."""

    def __init__(self, model, X: Tensor, Y: Tensor) -> None:
        self.d = model.dim
        self.X, self.Y = X.numpy(), Y.numpy()
        self.noise = model.noise
        P, _ = model.fit_covariance(X)
        self.P_data = None if P is None else P.numpy()
        # forgetting: reading i counts with variance sigma_n^2 / w_i (1.0 leaves every bit)
        self.sqrt_w = 1.0 if model.weights is None else np.sqrt(model.weights.numpy())
        self.center0 = model.center0.numpy()
        self.P = None if model.center_cov is None else model.center_precision.numpy()
        self.tau2 = (model.tau**2).numpy()
        self.log_c_model, self.log_c_std = model.log_c_model, model.log_c_std
        self.log_beta_std = model.log_beta_std
        self.f_inf, self.f_inf_std = model.f_inf, model.f_inf_std
        self.shape_std, self.s_index = model.shape_std, model._s_index
        if self.shape_std > 0:
            self.lam, self.V = model._lam.numpy(), model._V.numpy()
        else:
            self.B = model.B.numpy()

    def __call__(self, theta: np.ndarray) -> tuple[float, np.ndarray]:
        with np.errstate(all="ignore"):  # an overflow gives inf/nan: the caller rejects it
            return self._evaluate(theta)

    def _evaluate(self, theta: np.ndarray) -> tuple[float, np.ndarray]:
        d = self.d
        mu, log_c, log_beta = theta[:d], theta[d], theta[d + 1]
        c, beta = np.exp(log_c), np.exp(log_beta)
        D = self.X - mu
        if self.shape_std > 0:
            s = theta[self.s_index : self.s_index + d]
            lam = self.lam * np.exp(s)
            DV = D @ self.V
            BD = (DV * lam) @ self.V.T
        else:
            BD = D @ self.B
        q = (BD * D).sum(-1)
        g = c + beta * q
        background = self.f_inf + (theta[d + 2] if self.f_inf_std > 0 else 0.0)
        if self.P_data is None:
            r = self.sqrt_w * (self.Y - background - g**-0.5) / self.noise
            w = self.sqrt_w * r / self.noise
            data = float((r**2).sum())
        else:  # gls
            e = self.Y - background - g**-0.5
            w = self.P_data @ e
            data = float(e @ w)
        # d(data / 2)/d theta = -w . df/dtheta, df/dg = -0.5 g^-1.5
        a = -w * (-0.5 * g**-1.5)  # n: weight of dg/dtheta
        grad = np.empty_like(theta)
        grad[:d] = -2.0 * beta * (a @ BD)
        grad[d] = c * a.sum()
        grad[d + 1] = beta * (a @ q)
        if self.f_inf_std > 0:
            grad[d + 2] = -w.sum()
        if self.shape_std > 0:
            grad[self.s_index : self.s_index + d] = beta * (a @ (DV**2)) * lam
        dmu = mu - self.center0
        w = dmu / self.tau2 if self.P is None else self.P @ dmu
        pen = dmu @ w
        grad[:d] += w
        z = (log_c - self.log_c_model) / self.log_c_std
        pen += z**2
        grad[d] += z / self.log_c_std
        pen += (log_beta / self.log_beta_std) ** 2
        grad[d + 1] += log_beta / self.log_beta_std**2
        if self.f_inf_std > 0:
            pen += (theta[d + 2] / self.f_inf_std) ** 2
            grad[d + 2] += theta[d + 2] / self.f_inf_std**2
        if self.shape_std > 0:
            s = theta[self.s_index :]
            pen += (s**2).sum() / self.shape_std**2
            grad[self.s_index :] += s / self.shape_std**2
        return float(0.5 * data + 0.5 * pen), grad
