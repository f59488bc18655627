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
given) by L-BFGS-B from several starts: the previous fit, the prior mean, and the weighted
linear least-squares solution of :math:`g_i - \mathbf x_i^\top B \mathbf x_i = a +
\mathbf w^\top \mathbf x_i` (exact for :math:`\beta = 1`). Uncertainty: the Laplace
(Gauss-Newton) covariance :math:`C` of :math:`\hat\theta`, propagated to :math:`f` by the
Jacobian :math:`J(\mathbf x) = \partial f / \partial\theta`. What the form misses is modelled
by a residual GP (zero mean, fixed full-precision RBF kernel with the *machine-scale* precision
:math:`\hat\beta B / (2\hat c)`, i.e. the physics-informed kernel at the fitted optimum,
amplitude ``residual_std``) conditioned on the
residuals :math:`y_i - f(\mathbf x_i; \hat\theta)`:

.. math::
    \mu(\mathbf x) = f(\mathbf x;\hat\theta) + \mathbf k(\mathbf x)^\top K^{-1}\mathbf r, \qquad
    \sigma^2(\mathbf x) = J C J^\top + k(\mathbf x, \mathbf x) - \mathbf k^\top K^{-1}\mathbf k .
"""

from __future__ import annotations

import math

import numpy as np
import scipy.linalg
import scipy.optimize
import torch
from torch import Tensor

from pigp_torch._lbfgsb import minimize_lbfgsb
from pigp_torch._utils import DTYPE, as_knob_tensor, check_bounds
from pigp_torch.prior import PhysicsPrior


class InverseSqrtPeakModel:
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
            not the model rings; 3 by default, 1.5 stalled runs near the optimum).
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
            Hessians differ from the model ring's by 5-30 % along these directions. ``0``
            (default) keeps :math:`B` fixed.
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
        max_iter: int = 300,
    ) -> None:
        self.bounds = check_bounds(bounds)
        d = self.bounds.shape[1]
        if prior.dim != d:
            raise ValueError(f"prior has {prior.dim} knobs, bounds have {d}")
        self.noise = float(prior.noise if noise is None else noise)
        for name, v in (
            ("noise", self.noise),
            ("center_std", center_std),
            ("log_c_std", log_c_std),
            ("log_beta_std", log_beta_std),
            ("center_cov_scale", center_cov_scale),
            ("center_floor_std", center_floor_std),
        ):
            if not (math.isfinite(float(v)) and float(v) > 0):
                raise ValueError(f"{name} must be positive and finite, got {v}")
        for name, v in (
            ("residual_std", residual_std),
            ("f_inf_std", f_inf_std),
            ("shape_std", shape_std),
        ):
            if not (math.isfinite(float(v)) and float(v) >= 0):
                raise ValueError(f"{name} must be >= 0 and finite, got {v}")
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
        self.max_iter = int(max_iter)
        self.theta: Tensor | None = None
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

    def box_optimum(self, tol: float = 1e-9) -> tuple[Tensor, Tensor]:
        r"""The form's maximizer inside the knob box and which knobs sit on a bound there.

        :math:`\hat{\mathbf x} = \arg\min_{\mathbf x \in \text{box}} (\mathbf x -
        \hat{\boldsymbol\mu})^\top B (\mathbf x - \hat{\boldsymbol\mu})`, the projection of
        the fitted centre onto the box in the metric of :math:`B` (:math:`c` and :math:`\beta` do
        not move it): :math:`\hat{\boldsymbol\mu}` itself when it lies inside. Solved exactly as
        a bounded least-squares problem (``scipy.optimize.lsq_linear``, BVLS). Returns
        ``(x_hat, active)``, ``active`` a boolean ``d`` mask of the knobs at a bound with the
        form still rising outward (relative tolerance ``tol`` of the half-range)."""
        mu = self.center()
        inside = (mu >= self.bounds[0]) & (mu <= self.bounds[1])
        if bool(inside.all()):
            return mu, torch.zeros(self.dim, dtype=torch.bool)
        B = self.shape()
        A = torch.linalg.cholesky(B).T.numpy()  # B = L L^T: minimize |L^T (x - mu)|^2
        res = scipy.optimize.lsq_linear(
            A, A @ mu.numpy(), bounds=(self.bounds[0].numpy(), self.bounds[1].numpy()),
            method="bvls", tol=1e-12,
        )  # fmt: skip
        x = torch.from_numpy(res.x).to(DTYPE)
        grad = B @ (x - mu)  # half the quadratic's gradient: > 0 at a lower bound (< 0 at an
        # upper one) means the unconstrained minimum lies beyond that bound
        slack = tol * (self.bounds[1] - self.bounds[0]) / 2
        active = ((x <= self.bounds[0] + slack) & (grad > 0)) | (
            (x >= self.bounds[1] - slack) & (grad < 0)
        )
        return x, active

    def regret_metric(self) -> Tensor:
        r"""``d x d`` matrix :math:`M` with which an error :math:`\boldsymbol\delta` of the
        fitted centre costs :math:`\tfrac12\,\beta\,g(\hat{\mathbf x})^{-3/2}\,
        \boldsymbol\delta^\top M \boldsymbol\delta` (to second order) at the box optimum
        :math:`\hat{\mathbf x}` of :meth:`box_optimum`.

        With the free knobs :math:`F` and the active ones :math:`A` (fixed at their bound), the
        box optimum is :math:`\hat{\mathbf x}_F = \boldsymbol\mu_F - B_{FF}^{-1} B_{FA}
        (\mathbf b_A - \boldsymbol\mu_A)`, so :math:`P = \partial\hat{\mathbf x}_F /
        \partial\boldsymbol\mu = [I \;\; B_{FF}^{-1}B_{FA}]`, and the loss on the face is
        quadratic with Hessian :math:`\beta g^{-3/2} B_{FF}` (the gradient of :math:`g`
        vanishes along the face): :math:`M = P^\top B_{FF} P`, which is
        :math:`B` less the Schur complement :math:`B_{AA} - B_{AF}B_{FF}^{-1}B_{FA}` in the
        active block (how far the centre lies beyond the face does not matter). Inside the box
        :math:`M = B`."""
        B = self.shape()
        _, active = self.box_optimum()
        if not bool(active.any()):
            return B
        F = ~active
        M = B.clone()
        BAA = B[active][:, active]
        if bool(F.any()):
            BAF = B[active][:, F]
            schur = BAA - BAF @ torch.linalg.solve(B[F][:, F], BAF.T)
        else:
            schur = BAA
        idx = active.nonzero().squeeze(-1)
        M[idx.unsqueeze(-1), idx] -= schur
        return M

    def peak(self) -> float:
        r"""The fitted peak value :math:`f_\infty + \hat c^{-1/2}`."""
        return float(self.background()) + math.exp(-0.5 * float(self._fitted()[self.dim]))

    def _fitted(self) -> Tensor:
        if self.theta is None:
            raise RuntimeError("fit() the model first")
        return self.theta

    # -- fitting --------------------------------------------------------------------------------
    def _neg_log_post(self, theta: Tensor, X: Tensor, Y: Tensor) -> Tensor:
        d = self.dim
        r = (Y - self.form(X, theta)) / self.noise
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
        return 0.5 * (r**2).sum() + 0.5 * pen

    def _linear_start(self, X: Tensor, Y: Tensor) -> Tensor | None:
        r"""Weighted least squares of :math:`g_i - \mathbf x_i^\top B\mathbf x_i = a +
        \mathbf w^\top\mathbf x_i` (:math:`\beta=1`); weights from the delta method,
        :math:`\sigma_{g} = 2\sigma_n (y - f_\infty)^{-3}`."""
        n, d = X.shape
        if n < d + 2:
            return None
        e = (Y - self.f_inf).clamp_min(self.noise)
        w = e**3
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

    def fit(self, X, Y) -> float:
        r"""MAP fit to ``X`` (``n x d``), ``Y`` (``n``); returns the negative log posterior.

        Starts: the previous fit (warm start), :meth:`prior_theta` and the linear least-squares
        solution; the best end point wins. Then the Laplace covariance and the residual GP.

        Raises:
            ValueError: shapes or non-finite data.
        """
        X, _ = as_knob_tensor(X, self.dim, name="X")
        Y = torch.as_tensor(Y, dtype=DTYPE).reshape(-1)
        if Y.shape[0] != X.shape[0] or not torch.isfinite(Y).all():
            raise ValueError("Y must be finite with one value per row of X")
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

    def log_evidence(self) -> float:
        r"""Laplace estimate of the log marginal likelihood of the last :meth:`fit`'s data
        under this model (the residual GP not included):

        .. math::
            \log Z \approx -\tfrac12\|\mathbf r\|^2 - \tfrac12\,\mathrm{pen}(\hat\theta)
            - \tfrac n2 \log(2\pi\sigma_n^2) + \tfrac12\log\det\Lambda_0
            - \tfrac12\log\det A,

        :math:`\Lambda_0` the prior precision of :math:`\theta`, :math:`A = J^\top J/\sigma_n^2
        + \Lambda_0` (Gauss-Newton). Two models of the same readings compare by it (a
        difference of 3 is odds of 20 to 1)."""
        if self.theta is None:
            raise RuntimeError("fit() the model first")
        n = self._n
        return (
            -self.neg_log_post
            - 0.5 * n * math.log(2 * math.pi * self.noise**2)
            + 0.5 * self._log_det_prior
            - 0.5 * self._log_det_A
        )

    def _laplace(self, X: Tensor) -> None:
        J = self.jacobian(X)
        tail = [self.log_c_std**-2, self.log_beta_std**-2]
        if self.f_inf_std > 0:
            tail.append(self.f_inf_std**-2)
        if self.shape_std > 0:
            tail += [self.shape_std**-2] * self.dim
        tail = torch.diag(torch.tensor(tail, dtype=DTYPE))
        if self.center_cov is None:  # the box prior: diagonal, as before the ensemble option
            prior_prec = torch.diag(torch.cat([self.tau**-2, tail.diagonal()]))
        else:
            prior_prec = torch.block_diag(self.center_precision, tail)
        A = J.T @ J / self.noise**2 + prior_prec
        L = torch.linalg.cholesky(A)
        cov = torch.cholesky_inverse(L)
        self._log_det_A = 2.0 * float(torch.log(L.diagonal()).sum())
        self._log_det_prior = float(torch.linalg.slogdet(prior_prec)[1])
        self.cov = (cov + cov.T) / 2

    def residual_precision(self) -> Tensor:
        r"""Precision of the residual kernel: :math:`\hat\beta B / (2\hat c)`, the Hessian of
        :math:`-\log(f - f_\infty)` at the fitted optimum, halved (the PI-GP convention)."""
        theta = self._fitted()
        d = self.dim
        return torch.exp(theta[d + 1] - theta[d]) * self.shape(theta) / 2

    def _k_res(self, A: Tensor, Bx: Tensor) -> Tensor:
        D = A.unsqueeze(-2) - Bx.unsqueeze(-3)
        q = ((D @ self._res_prec) * D).sum(-1)
        return self.residual_std**2 * torch.exp(-0.5 * q)

    def _residual_gp(self, X: Tensor, Y: Tensor) -> None:
        self._X = X
        if self.residual_std == 0:
            return
        self._res_prec = self.residual_precision()
        with torch.no_grad():
            r = Y - self.form(X)
        K = self._k_res(X, X) + self.noise**2 * torch.eye(X.shape[0], dtype=DTYPE)
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

    def predict_with_grad(self, X: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        r""":meth:`predict` and its gradients in ``X`` in closed form (no autograd graph):
        ``(mu, sd, dmu, dsd)``, ``n``, ``n``, ``n x d``, ``n x d``.

        With :math:`\mathbf D = \mathbf x - \hat{\boldsymbol\mu}`, :math:`g = c + \beta
        \mathbf D^\top B\mathbf D` and :math:`\mathbf w = C\,\mathbf j` (:math:`\mathbf j`
        the row of :meth:`jacobian`):

        .. math::
            \nabla f = -\beta g^{-3/2} B\mathbf D, \qquad
            \nabla(\mathbf j^\top C\mathbf j) = 2 \sum_k w_k \nabla j_k,

        :math:`\nabla j_k` from :math:`j_k = -\tfrac12 g^{-3/2}\,\partial g/\partial\theta_k`
        (:math:`\nabla g^{-3/2} = -3\beta g^{-5/2} B\mathbf D`). The residual GP adds
        :math:`\nabla k_i = -k_i P(\mathbf x - \mathbf x_i)` to the mean (weights
        :math:`\alpha`) and :math:`-2\sum_i u_i \nabla k_i`, :math:`\mathbf u = K^{-1}\mathbf
        k`, to the variance; :math:`\nabla\sigma = \nabla\sigma^2 / (2\sigma)` (zero where the
        variance sits at its floor).

        Computed in NumPy from the fit's quantities (cached once per fit): the acquisition
        search calls this hundreds of times an ask on ``k x d`` arrays of a few starts, where
        each torch call costs more than its arithmetic. A test checks it against autograd of
        :meth:`predict`."""
        out = self.predict_numpy(X.detach().numpy())
        return tuple(torch.from_numpy(np.ascontiguousarray(a)) for a in out)

    def predict_numpy(self, x: np.ndarray) -> tuple[np.ndarray, ...]:
        """:meth:`predict_with_grad` on and to NumPy arrays: ``(mu, sd, dmu, dsd)`` at ``n x d``
        settings ``x``."""
        st = self._prediction_state()
        pt = self._form_terms(st, x)
        beta, BD = st["beta"], pt["BD"]
        mu = st["background"] + pt["g"] ** -0.5
        dmu = (2.0 * pt["dfdg"])[..., None] * beta * BD
        J = pt["J"]
        W = J @ st["cov"]  # n x p
        var = (W * J).sum(-1)
        dvar = 2.0 * self._contract_grad_j(st, pt, W)
        if self.residual_std > 0:
            Dr = x[..., None, :] - st["Xr"]  # n x m x d
            PDr = Dr @ st["P"]
            Ks = self.residual_std**2 * np.exp(-0.5 * (PDr * Dr).sum(-1))  # n x m
            mu = mu + Ks @ st["alpha"]
            dmu = dmu - ((Ks * st["alpha"])[..., None] * PDr).sum(-2)
            Lr = st["L"]  # K = L L^T: U = K^-1 k by two triangular solves
            U = np.swapaxes(_cho_solve(Lr, np.swapaxes(Ks, -1, -2)), -1, -2)
            var = var + self.residual_std**2 - (Ks * U).sum(-1)
            dvar = dvar + 2.0 * ((U * Ks)[..., None] * PDr).sum(-2)
        floor = var <= 1e-18
        sd = np.sqrt(np.maximum(var, 1e-18))
        dsd = np.where(floor[..., None], 0.0, dvar / (2 * sd)[..., None])
        return mu, sd, dmu, dsd

    def _prediction_state(self) -> dict:
        """The fitted quantities of :meth:`predict_with_grad` as NumPy arrays, computed once per
        fit (the cache is keyed on the very tensors of the fit, which a new fit replaces)."""
        theta = self._fitted()
        key = (theta, self.cov, getattr(self, "_L", None), getattr(self, "_X", None))
        cached = getattr(self, "_np_state", None)
        if cached is not None and all(a is b for a, b in zip(cached["key"], key, strict=True)):
            return cached
        d = self.dim
        st = {
            "key": key,
            "mu": theta[:d].numpy(),
            "B": self.shape(theta).numpy(),
            "c": float(torch.exp(theta[d])),
            "beta": float(torch.exp(theta[d + 1])),
            "background": float(self.background(theta)),
            "cov": self.cov.numpy(),
        }
        if self.shape_std > 0:
            st["V"] = self._V.numpy()
            st["lam"] = (self._lam * torch.exp(theta[self._s_index : self._s_index + d])).numpy()
        if self.residual_std > 0:
            st["Xr"], st["P"] = self._X.numpy(), self._res_prec.numpy()
            st["alpha"], st["L"] = self._alpha.numpy(), self._L.numpy()
        self._np_state = st
        return st

    def _form_terms(self, st: dict, x: np.ndarray) -> dict:
        r"""The form's pieces at ``n x d`` settings ``x`` (NumPy, fitted :math:`\theta` from
        ``st``): :math:`\mathbf D`, :math:`B\mathbf D`, :math:`q`, :math:`g`,
        :math:`\partial f/\partial g = -\tfrac12 g^{-3/2}`, :math:`\mathbf D^\top V` (shape
        fitted) and the ``n x p`` rows :math:`J` of :meth:`jacobian`."""
        c, beta = st["c"], st["beta"]
        D = x - st["mu"]
        BD = D @ st["B"]
        q = (BD * D).sum(-1)
        g = c + beta * q
        dfdg = -0.5 * g**-1.5
        cols = [-2.0 * beta * BD, np.broadcast_to(c, q.shape)[..., None], (beta * q)[..., None]]
        J = np.concatenate(cols, -1) * dfdg[..., None]
        if self.f_inf_std > 0:
            J = np.concatenate([J, np.ones_like(q)[..., None]], -1)
        DV = None
        if self.shape_std > 0:
            DV = D @ st["V"]
            J = np.concatenate([J, (beta * DV**2 * st["lam"]) * dfdg[..., None]], -1)
        return {"D": D, "BD": BD, "q": q, "g": g, "dfdg": dfdg, "DV": DV, "J": J}

    def _contract_grad_j(self, st: dict, pt: dict, A: np.ndarray) -> np.ndarray:
        r""":math:`\sum_k a_k \nabla_{\mathbf x} j_k` for ``n x p`` weights ``A`` (one row per
        setting), ``n x d``: with :math:`j_k = \tfrac{\partial f}{\partial g}
        \tfrac{\partial g}{\partial\theta_k}`, :math:`\nabla (\partial f/\partial g) =
        \tfrac32\beta g^{-5/2} B\mathbf D` and the gradients of :math:`\partial
        g/\partial\theta_k` (:math:`-2\beta B` for the centre, :math:`2\beta B\mathbf D` for
        :math:`\log\beta`, :math:`2\beta\lambda_k e^{s_k}(\mathbf v_k^\top\mathbf D)\mathbf
        v_k` for a shape log-scale; none for :math:`\log c` and the background)."""
        d, c, beta = self.dim, st["c"], st["beta"]
        BD, q, g, DV = pt["BD"], pt["q"], pt["g"], pt["DV"]
        # sum_k a_k dg/dtheta_k, then the same with each dg/dtheta_k differentiated in x
        adg = -2.0 * beta * (A[..., :d] * BD).sum(-1) + A[..., d] * c + A[..., d + 1] * beta * q
        inner = -2.0 * beta * (A[..., :d] @ st["B"]) + (2.0 * beta * A[..., d + 1])[..., None] * BD
        if self.shape_std > 0:
            i = self._s_index
            As = A[..., i : i + d]
            adg = adg + (As * beta * DV**2 * st["lam"]).sum(-1)
            inner = inner + 2.0 * beta * ((As * st["lam"] * DV) @ st["V"].T)
        return (adg * 1.5 * beta * g**-2.5)[..., None] * BD + pt["dfdg"][..., None] * inner

    def centre_information_with_grad(self, X: Tensor) -> tuple[Tensor, Tensor]:
        r"""How much one more reading at each of ``n x d`` settings shrinks
        :math:`\mathrm{tr}(B\,C_\mu)`, :math:`C_\mu` the Laplace covariance of the fitted
        centre, and its ``n x d`` gradient in closed form.

        With :math:`\mathbf j` the row of :meth:`jacobian`, :math:`\mathbf v = C\mathbf j`,
        :math:`N = \mathbf v_\mu^\top B\,\mathbf v_\mu` and :math:`S = \sigma_n^2 +
        \mathbf j^\top C\mathbf j` (Sherman-Morrison), the reduction is :math:`I = N / S` and

        .. math:: \nabla I = \sum_k \bigl(2\,(C_{\cdot\mu} B\,\mathbf v_\mu)_k
                  - 2 I\, v_k\bigr)\,\nabla j_k \,/\, S

        (:meth:`_contract_grad_j`). Units: knob units squared (of the trace), per knob unit
        for the gradient."""
        info, grad = self.centre_information_numpy(X.detach().numpy())
        return torch.from_numpy(info), torch.from_numpy(np.ascontiguousarray(grad))

    def centre_information_numpy(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`centre_information_with_grad` on and to NumPy arrays (``n``, ``n x d``)."""
        st = self._prediction_state()
        pt = self._form_terms(st, x)
        J, cov, d = pt["J"], st["cov"], self.dim
        V = J @ cov
        BVmu = V[..., :d] @ st["B"]
        S = self.noise**2 + (V * J).sum(-1)
        info = (BVmu * V[..., :d]).sum(-1) / S
        A = 2.0 * (BVmu @ cov[:d, :]) - 2.0 * info[..., None] * V
        grad = self._contract_grad_j(st, pt, A) / S[..., None]
        return info, grad


def _cho_solve(L: np.ndarray, b: np.ndarray) -> np.ndarray:
    """:math:`(L L^\top)^{-1} b` for a lower Cholesky factor ``L`` (``m x m``) and ``m x k``
    ``b``."""
    y = scipy.linalg.solve_triangular(L, b, lower=True, check_finite=False)
    return scipy.linalg.solve_triangular(L.T, y, lower=False, check_finite=False)


class _NumpyObjective:
    r"""The negative log posterior :meth:`InverseSqrtPeakModel._neg_log_post` and its gradient
    in closed form, in NumPy, for the L-BFGS-B fit:
    :math:`\nabla = -J^\top \mathbf r / \sigma_n + \tfrac12 \nabla\text{pen}`, :math:`J` as in
    :meth:`InverseSqrtPeakModel.jacobian` and :math:`\mathbf r = (\mathbf y - f)/\sigma_n`.

    The arrays have 13-100 entries: at these sizes each torch call costs more
    than its arithmetic, and the fit evaluates it hundreds of times an ask.
    A test checks it against the torch version to round-off."""

    def __init__(self, model: InverseSqrtPeakModel, X: Tensor, Y: Tensor) -> None:
        self.d = model.dim
        self.X, self.Y = X.numpy(), Y.numpy()
        self.noise = model.noise
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
        r = (self.Y - background - g**-0.5) / self.noise
        # d(0.5 |r|^2)/d theta = -r/noise . df/dtheta, df/dg = -0.5 g^-1.5
        a = -(r / self.noise) * (-0.5 * g**-1.5)  # n: weight of dg/dtheta
        grad = np.empty_like(theta)
        grad[:d] = -2.0 * beta * (a @ BD)
        grad[d] = c * a.sum()
        grad[d + 1] = beta * (a @ q)
        if self.f_inf_std > 0:
            grad[d + 2] = -(r / self.noise).sum()
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
        return float(0.5 * (r**2).sum() + 0.5 * pen), grad
