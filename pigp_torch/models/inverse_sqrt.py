r"""The physics form of the loss rate, fitted online: an inverse-square-root peak with known shape.

Why this form. The vertical emittance of a weakly coupled ring is, to a good approximation, a
quadratic bowl in the skew-quadrupole strengths, and the Touschek loss rate scales like
:math:`1/\sigma_y \propto \varepsilon_y^{-1/2}`. Hence

.. math::
    f(\mathbf x) = f_\infty + g(\mathbf x)^{-1/2}, \qquad
    g(\mathbf x) = c + \beta\,(\mathbf x - \boldsymbol\mu)^\top B\, (\mathbf x - \boldsymbol\mu),

with :math:`g = (f - f_\infty)^{-2}` exactly quadratic. The *shape* :math:`B` is a property of the
optics and barely depends on the error seed; it follows from the physics prior of the model ring:
the Hessian of :math:`\log(f - f_\infty)` at the model's optimum is :math:`-B_m / c_m` with
:math:`c_m = (f(\mathbf x_0) - f_\infty)^{-2}`, so with :math:`\Sigma = -H/2`,

.. math:: B = 2\, c_m\, \Sigma .

The machines' own shapes resemble the model's (the optics decide the directions), while their
minima :math:`c` and centres :math:`\boldsymbol\mu` are unrelated to the model's. Any one ring's
shape carries its own errors;
the mean shape over an error ensemble of model rings
(:attr:`PhysicsPrior.peak_shape <pigp_torch.prior.PhysicsPrior>`, option ``shape``) averages
them out and is the better estimate for an unseen machine. So the machine-specific unknowns are
:math:`\boldsymbol\mu` (``d``), :math:`\log c` and a global :math:`\log\beta`
(:math:`\beta\approx1`): ``d + 2`` numbers instead of a GP's whole function.

Fit (MAP, Gaussian noise of known :math:`\sigma_n` on :math:`f`):

.. math::
    \hat\theta = \arg\min_\theta \tfrac{1}{2\sigma_n^2}\sum_i (y_i - f(\mathbf x_i;\theta))^2
    + \tfrac12\Big\|\tfrac{\boldsymbol\mu - \boldsymbol\mu_0}{\tau\,\mathbf h}\Big\|^2
    + \tfrac{(\log c - \log c_m)^2}{2 s_c^2} + \tfrac{(\log\beta)^2}{2 s_\beta^2},

(:math:`\mathbf h` the knob half-ranges, :math:`\boldsymbol\mu_0` the box centre unless
given; with the option ``gls`` the first sum becomes :math:`\tfrac12\mathbf
r^\top\Sigma^{-1}\mathbf r`, see the end of this docstring) by L-BFGS-B from several starts:
the previous fit, the prior mean, and the weighted linear least-squares solution of
:math:`g_i - \mathbf x_i^\top B \mathbf x_i = a + \mathbf w^\top \mathbf x_i` (exact for
:math:`\beta = 1`). Uncertainty: the Laplace (Gauss-Newton) covariance :math:`C` of
:math:`\hat\theta`, propagated to :math:`f` by the
Jacobian :math:`J(\mathbf x) = \partial f / \partial\theta`. What the form misses is modelled
by a residual GP (zero mean, fixed full-precision RBF kernel with the *machine-scale* precision
:math:`\hat\beta B / (2\hat c)`, i.e. the physics-informed kernel at the fitted optimum,
amplitude ``residual_std``) conditioned on the
residuals :math:`y_i - f(\mathbf x_i; \hat\theta)`:

.. math::
    \mu(\mathbf x) = f(\mathbf x;\hat\theta) + \mathbf k(\mathbf x)^\top K^{-1}\mathbf r, \qquad
    \sigma^2(\mathbf x) = J C J^\top + k(\mathbf x, \mathbf x) - \mathbf k^\top K^{-1}\mathbf k .

Generalized least squares (option ``gls``, off by default; needs ``residual_std > 0``). A
machine is not exactly the form: its :math:`g` is not exactly quadratic away from the peak, and
the departure is smooth on the scale of the peak's width. Fitted as independent noise, such a
departure can pull the fitted centre (a biased :math:`\boldsymbol\mu` buys a smaller misfit).
With ``gls`` the readings' errors are those of the residual GP plus the noise,
:math:`\mathbf r \sim \mathcal N(0, \Sigma)`, :math:`\Sigma = K + \sigma_n^2 I` (:math:`K`
the residual kernel above at the told settings, its precision from the :math:`\theta` the fit
starts from: the previous fit, else :math:`\theta_0`). The data term of the fit is then
:math:`\tfrac12\mathbf r^\top\Sigma^{-1}\mathbf r`, the Laplace precision
:math:`J^\top\Sigma^{-1}J + \Lambda_0`, and the evidence has :math:`\log\det\Sigma` in
place of :math:`n\log\sigma_n^2`: the form and its residual GP as one Gaussian model of the
readings (universal kriging), in which a smooth departure is explained by the GP rather than
by the centre. The information of one more reading
(:meth:`InverseSqrtPeakModel.centre_information`) still treats that reading's error as
independent of the told ones.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from pigp_torch._utils import DTYPE, as_knob_tensor, check_bounds
from pigp_torch._utils.lbfgsb import minimize_lbfgsb
from pigp_torch.models._inverse_sqrt_fit import FitTerms, _NumpyObjective
from pigp_torch.models._inverse_sqrt_numpy import BoxAnalysis, NumpyPrediction
from pigp_torch.prior import PhysicsPrior


class InverseSqrtPeakModel(FitTerms, NumpyPrediction, BoxAnalysis):
    r"""Online fit of :math:`f = f_\infty + (c + \beta (\mathbf x-\boldsymbol\mu)^\top B
    (\mathbf x-\boldsymbol\mu))^{-1/2}` with :math:`B` from a physics prior (module docstring).

    Args:
        prior: the model ring's :class:`~pigp_torch.prior.PhysicsPrior` (gives :math:`B`,
            :math:`f_\infty`, :math:`c_m`).
        bounds: ``2 x d`` knob bounds (the centre prior is relative to them).
        noise: measurement noise :math:`\sigma_n` of the objective (default: ``prior.noise``).
        center_std: :math:`\tau`, prior std of each centre coordinate in half-ranges (the
            isotropic "box" prior, used when ``center_cov`` is ``None``).
        center_mean: ``d`` prior mean :math:`\boldsymbol\mu_0` of the centre (knob units;
            default ``None``: the box centre, i.e. the knobs' zero on a symmetric box).
        center_cov: ``d x d`` covariance :math:`C_e` of machine optima over an ensemble of
            model rings (:attr:`PhysicsPrior.center_cov <pigp_torch.prior.PhysicsPrior>`); the
            centre prior is then :math:`\mathcal N(\boldsymbol\mu_0, C_\mu)` with
            :math:`C_\mu = k\,C_e + (s_0 \mathbf h)^2 I`.
        center_cov_scale: :math:`k`, inflation of the ensemble covariance (the machines are
            not the model rings; default 3).
        center_floor_std: :math:`s_0`, isotropic floor in half-ranges, so that directions in
            which the ensemble hardly varies are not frozen.
        log_c_std: :math:`s_c`, prior std of :math:`\log c` around :math:`\log c_m`.
        log_beta_std: :math:`s_\beta`, prior std of :math:`\log\beta` around 0.
        residual_std: amplitude of the residual GP (objective units; ``0`` switches it off).
        f_inf_std: if ``> 0``, the background is fitted too, as :math:`f_\infty + \delta` with
            :math:`\delta \sim \mathcal N(0, s_f^2)` (objective units; the prior's
            :math:`f_\infty` belongs to the model ring); ``0`` (default) keeps :math:`f_\infty`
            fixed.
        shape: ``d x d`` shape :math:`B` to use instead of the model ring's
            :math:`2 c_m \Sigma`, e.g. the ensemble mean
            :attr:`PhysicsPrior.peak_shape <pigp_torch.prior.PhysicsPrior>` (``None``: the
            model ring's).
        shape_std: if ``> 0``, the shape is fitted too, along the eigenvectors
            :math:`\mathbf v_k` of :math:`B` (eigenvalues :math:`\lambda_k`):
            :math:`B(\mathbf s) = \sum_k \lambda_k e^{s_k} \mathbf v_k \mathbf v_k^\top` with
            :math:`s_k \sim \mathcal N(0, s_B^2)` (``d`` more parameters); the machines' own
            Hessians differ from the model ring's mostly in scale along these directions. ``0``
            (default) keeps :math:`B` fixed.
        gls: fit with the readings' covariance :math:`\Sigma = K + \sigma_n^2 I` of the
            residual GP (module docstring); ``False`` (default), or
            ``residual_std = 0``: independent noise, :math:`\Sigma = \sigma_n^2 I`.
        max_iter: L-BFGS-B iterations per start.

    Raises:
        ValueError: knob count of ``prior`` and ``bounds`` differ, non-positive scales, or a
            ``shape`` that is not ``d x d`` positive definite.
    """

    def __init__(
        self,
        prior: PhysicsPrior,
        bounds,
        *,
        noise: float | None = None,
        center_std: float = 1.0,
        log_c_std: float = 1.5,
        log_beta_std: float = 0.3,
        residual_std: float = 0.05,
        f_inf_std: float = 0.0,
        center_cov=None,
        center_mean=None,
        center_cov_scale: float = 3.0,
        center_floor_std: float = 0.22,
        shape=None,
        shape_std: float = 0.0,
        gls: bool = False,
        max_iter: int = 300,
    ) -> None:
        self.bounds = check_bounds(bounds)
        d = self.bounds.shape[1]
        if prior.dim != d:
            raise ValueError(f"prior has {prior.dim} knobs, bounds have {d}")
        self.noise = float(prior.noise if noise is None else noise)
        _check_scales(
            positive={"noise": self.noise, "center_std": center_std, "log_c_std": log_c_std,
                      "log_beta_std": log_beta_std, "center_cov_scale": center_cov_scale,
                      "center_floor_std": center_floor_std},
            nonnegative={"residual_std": residual_std, "f_inf_std": f_inf_std,
                         "shape_std": shape_std},
        )  # fmt: skip
        self.f_inf_std = float(f_inf_std)
        self.f_inf = float(prior.f_inf)
        self.log_c_model = -2.0 * math.log(prior.f_x0 - prior.f_inf)
        if shape is None:
            self.B = 2.0 * math.exp(self.log_c_model) * prior.precision.to(DTYPE)
        else:
            self.B = torch.as_tensor(shape, dtype=DTYPE)
            if self.B.shape != (d, d) or not torch.linalg.eigvalsh(self.B).min() > 0:
                raise ValueError(f"shape must be a {d} x {d} positive-definite matrix")
        self.B = (self.B + self.B.T) / 2
        self.shape_std = float(shape_std)
        if self.shape_std > 0:  # eigenbasis of the fitted shape B(s)
            self._lam, self._V = torch.linalg.eigh(self.B)
        lower, upper = self.bounds
        self.center0 = (upper + lower) / 2
        if center_mean is not None:
            self.center0 = torch.as_tensor(center_mean, dtype=DTYPE).reshape(-1).clone()
            if self.center0.shape != (d,) or not torch.isfinite(self.center0).all():
                raise ValueError(f"center_mean must be {d} finite values")
        half = (upper - lower) / 2
        self.tau = float(center_std) * half
        self.center_cov = None if center_cov is None else torch.as_tensor(center_cov, dtype=DTYPE)
        if center_cov is None:
            self.center_precision = torch.diag(self.tau**-2)
        else:
            C = torch.as_tensor(center_cov, dtype=DTYPE)
            if C.shape != (d, d):
                raise ValueError(f"center_cov must be {d} x {d}, got {tuple(C.shape)}")
            C = float(center_cov_scale) * (C + C.T) / 2
            C = C + torch.diag((float(center_floor_std) * half) ** 2)
            self.tau = C.diagonal().sqrt()  # marginal stds (the linear start's clamp uses them)
            P = torch.cholesky_inverse(torch.linalg.cholesky(C))
            self.center_precision = (P + P.T) / 2
        self.log_c_std = float(log_c_std)
        self.log_beta_std = float(log_beta_std)
        self.residual_std = float(residual_std)
        self.gls = bool(gls) and self.residual_std > 0
        self._fit_cov: tuple | None = None  # (X, Sigma^-1, log det Sigma) of the last fit
        self.max_iter = int(max_iter)
        self.theta: Tensor | None = None
        self.weights: Tensor | None = None  # readings' weights of the last fit (None: all 1)
        self.cov: Tensor | None = None
        self._X: Tensor | None = None

    @property
    def dim(self) -> int:
        return self.B.shape[0]

    @property
    def n_params(self) -> int:
        r""":math:`\theta = (\boldsymbol\mu, \log c, \log\beta[, \delta][, \mathbf s])` has this
        length (:math:`\delta` with ``f_inf_std > 0``, :math:`\mathbf s` with ``shape_std > 0``)."""
        return self.dim + 2 + int(self.f_inf_std > 0) + self.dim * int(self.shape_std > 0)

    @property
    def _s_index(self) -> int:
        """Index of the first shape log-scale :math:`s_1` in :math:`\theta`."""
        return self.dim + 2 + int(self.f_inf_std > 0)

    def shape(self, theta: Tensor | None = None) -> Tensor:
        r"""The shape :math:`B(\mathbf s)` of ``theta`` (default: the fit); :math:`B` itself
        when the shape is not fitted."""
        if self.shape_std == 0:
            return self.B
        theta = self._fitted() if theta is None else theta
        scale = self._lam * torch.exp(theta[self._s_index : self._s_index + self.dim])
        return (self._V * scale) @ self._V.T

    # -- the parametric form -------------------------------------------------------------------
    def prior_theta(self) -> Tensor:
        r""":math:`\theta_0 = (\boldsymbol\mu_0, \log c_m, 0[, 0][, \mathbf 0])`."""
        tail = [self.log_c_model, 0.0] + [0.0] * (self.n_params - self.dim - 2)
        return torch.cat([self.center0, torch.tensor(tail, dtype=DTYPE)])

    def background(self, theta: Tensor | None = None):
        r"""The background :math:`f_\infty` (+ the fitted :math:`\delta`) of ``theta``
        (default: the fit)."""
        theta = self._fitted() if theta is None else theta
        return self.f_inf + theta[self.dim + 2] if self.f_inf_std > 0 else self.f_inf

    def g(self, X: Tensor, theta: Tensor) -> Tensor:
        r""":math:`g(\mathbf x;\theta)` for ``... x d`` settings."""
        d = self.dim
        D = X - theta[:d]
        return torch.exp(theta[d]) + torch.exp(theta[d + 1]) * ((D @ self.shape(theta)) * D).sum(-1)

    def form(self, X: Tensor, theta: Tensor | None = None) -> Tensor:
        r"""The parametric mean :math:`f_\infty + g^{-1/2}` (``theta`` default: the fit)."""
        theta = self._fitted() if theta is None else theta
        return self.background(theta) + torch.rsqrt(self.g(X, theta))

    def jacobian(self, X: Tensor, theta: Tensor | None = None) -> Tensor:
        r"""``n x n_params`` analytic :math:`\partial f/\partial\theta` at ``theta`` (default:
        the fitted :math:`\theta`)."""
        theta = self._fitted() if theta is None else theta
        d = self.dim
        D = X - theta[:d]
        BD = D @ self.shape(theta)
        q = (BD * D).sum(-1)
        c, beta = torch.exp(theta[d]), torch.exp(theta[d + 1])
        dfdg = -0.5 * (c + beta * q) ** -1.5
        dg = torch.cat(
            [-2.0 * beta * BD, c.expand(q.shape).unsqueeze(-1), (beta * q).unsqueeze(-1)], -1
        )
        J = dg * dfdg.unsqueeze(-1)
        if self.f_inf_std > 0:  # df/d(delta) = 1
            J = torch.cat([J, torch.ones_like(q).unsqueeze(-1)], -1)
        if self.shape_std > 0:  # dg/ds_k = beta lambda_k e^{s_k} (v_k . D)^2
            s = theta[self._s_index : self._s_index + d]
            dgs = beta * (D @ self._V) ** 2 * (self._lam * torch.exp(s))
            J = torch.cat([J, dgs * dfdg.unsqueeze(-1)], -1)
        return J

    def center(self) -> Tensor:
        r"""The fitted centre :math:`\hat{\boldsymbol\mu}` (may lie outside the bounds)."""
        return self._fitted()[: self.dim].clone()

    def peak(self) -> float:
        r"""The fitted peak value :math:`f_\infty + \hat c^{-1/2}`."""
        return float(self.background()) + math.exp(-0.5 * float(self._fitted()[self.dim]))

    def _fitted(self) -> Tensor:
        if self.theta is None:
            raise RuntimeError("fit() the model first")
        return self.theta

    # -- fitting --------------------------------------------------------------------------------
    def fit(self, X, Y, weights=None) -> float:
        r"""MAP fit to ``X`` (``n x d``), ``Y`` (``n``); returns the negative log posterior.
        ``weights`` (``n`` in (0, 1], default all 1): reading i counts with noise variance
        :math:`\sigma_n^2 / w_i` in the fit, its Laplace covariance and the residual GP.

        Starts: the previous fit (warm start), :meth:`prior_theta` and the linear least-squares
        solution; the best end point wins. Then the Laplace covariance and the residual GP.

        Raises:
            ValueError: shapes or non-finite data.
        """
        X, _ = as_knob_tensor(X, self.dim, name="X")
        Y = torch.as_tensor(Y, dtype=DTYPE).reshape(-1)
        if Y.shape[0] != X.shape[0] or not torch.isfinite(Y).all():
            raise ValueError("Y must be finite with one value per row of X")
        self.weights = None if weights is None else torch.as_tensor(weights, dtype=DTYPE)
        self._fit_cov = None  # Sigma from the theta the fit starts from
        self._fit_cov = (X, *self.fit_covariance(X))
        starts = [self.prior_theta()]
        if self.theta is not None:
            starts.insert(0, self.theta)
        lin = self._linear_start(X, Y)
        if lin is not None:
            starts.append(lin)

        # With the shape fitted, the search runs in z = theta / scale, the centre in units of its
        # prior std: the knobs' scale (~1e-2) against the log-scales' (~1) otherwise leaves
        # L-BFGS-B far from converged after max_iter steps. (Fixed shape: scale 1, as before.)
        scale = torch.ones(self.n_params, dtype=DTYPE)
        if self.shape_std > 0:
            scale[: self.dim] = self.tau
        scale_np = scale.numpy()

        evaluate = _NumpyObjective(self, X, Y)._evaluate
        unit = self.shape_std == 0  # scale 1: the products below would not change a bit

        def value_and_grad(z: np.ndarray) -> tuple[float, np.ndarray]:
            v, grad = evaluate(z if unit else z * scale_np)
            if not (math.isfinite(v) and np.isfinite(grad).all()):
                return 1e30, np.zeros_like(z)
            return v, grad if unit else grad * scale_np

        best = None
        with np.errstate(all="ignore"):  # an overflow gives inf/nan, which is rejected above
            for t0 in starts:
                res = minimize_lbfgsb(
                    value_and_grad, t0.detach().numpy() / scale_np, maxiter=self.max_iter
                )
                if best is None or res.fun < best[1]:
                    best = (torch.from_numpy(res.x * scale_np).to(DTYPE), float(res.fun))
        self.theta = best[0]
        self._laplace(X)
        self._residual_gp(X, Y)
        self.neg_log_post = best[1]
        self._n = X.shape[0]
        return best[1]

    def residual_precision(self, theta: Tensor | None = None) -> Tensor:
        r"""Precision of the residual kernel: :math:`\beta B / (2 c)`, the Hessian of
        :math:`-\log(f - f_\infty)` at the optimum of ``theta`` (default: the fit), halved (the
        PI-GP convention)."""
        theta = self._fitted() if theta is None else theta
        d = self.dim
        return torch.exp(theta[d + 1] - theta[d]) * self.shape(theta) / 2

    def _k_res(self, A: Tensor, Bx: Tensor, precision: Tensor | None = None) -> Tensor:
        """Residual kernel between ``A`` and ``Bx`` (precision default: the fit's)."""
        P = self._res_prec if precision is None else precision
        D = A.unsqueeze(-2) - Bx.unsqueeze(-3)
        q = ((D @ P) * D).sum(-1)
        return self.residual_std**2 * torch.exp(-0.5 * q)

    def _residual_gp(self, X: Tensor, Y: Tensor) -> None:
        self._X = X
        if self.residual_std == 0:
            return
        self._res_prec = self.residual_precision()
        with torch.no_grad():
            r = Y - self.form(X)
        K = self._k_res(X, X) + torch.diag(self.noise_variances(X.shape[0]))
        self._L = torch.linalg.cholesky(K)
        self._alpha = torch.cholesky_solve(r.unsqueeze(-1), self._L).squeeze(-1)

    # -- prediction -----------------------------------------------------------------------------
    def predict(self, X: Tensor) -> tuple[Tensor, Tensor]:
        r"""Posterior mean and standard deviation of :math:`f` at ``n x d`` settings
        (differentiable in ``X``)."""
        mu = self.form(X)
        J = self.jacobian(X)
        var = ((J @ self.cov) * J).sum(-1)
        if self.residual_std > 0:
            Ks = self._k_res(X, self._X)
            mu = mu + Ks @ self._alpha
            V = torch.cholesky_solve(Ks.transpose(-1, -2), self._L)
            var = var + self.residual_std**2 - (Ks * V.transpose(-1, -2)).sum(-1)
        return mu, var.clamp_min(1e-18).sqrt()


def _check_scales(positive: dict, nonnegative: dict) -> None:
    """Each of ``positive`` finite and > 0, each of ``nonnegative`` finite and >= 0."""
    for name, v in positive.items():
        if not (math.isfinite(float(v)) and float(v) > 0):
            raise ValueError(f"{name} must be positive and finite, got {v}")
    for name, v in nonnegative.items():
        if not (math.isfinite(float(v)) and float(v) >= 0):
            raise ValueError(f"{name} must be >= 0 and finite, got {v}")
