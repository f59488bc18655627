r"""A physics-structured GP prior mean: an inverse-square-root peak with learnable centre.

The Touschek loss rate of a coupled ring behaves as :math:`f \approx f_\infty + A/\sqrt{1 + q}`
with :math:`q` quadratic in the skew knobs (the vertical emittance is quadratic in them). The
model ring fixes the *shape* of :math:`q` (the prior's precision :math:`\Sigma`); the machine's
optimum :math:`\mu`, peak height :math:`A` and curvature scale :math:`s` are fitted online.
"""

from __future__ import annotations

import math

import torch
from gpytorch.means import Mean

from pigp_torch._utils import DTYPE
from pigp_torch.prior import PhysicsPrior


class PhysicsMean(Mean):
    r"""Prior mean :math:`m(\mathbf x) = f_\infty + A\,/\sqrt{1 + 2 s\,(\mathbf x - \mu)^\top
    \Sigma\, (\mathbf x - \mu)}`.

    With :math:`s = 1` the Hessian of :math:`\log(m - f_\infty)` at :math:`\mu` is
    :math:`-2\Sigma`, i.e. the model ring's Hessian :math:`H` (:math:`\Sigma = -H/2`).

    Parameters (``torch.nn.Parameter``): ``center`` :math:`\mu` (``d``, knob units), ``log_peak``
    :math:`\log A`, ``log_scale`` :math:`\log s` and ``log_eigen_scales`` (``n_eigen_scales``:
    extra log-scales of the curvature along the top eigenvectors of :math:`\Sigma`, see
    :meth:`quadratic`). Buffers: ``precision`` :math:`\Sigma` (``d x d``), its ``eigenvalues``
    (descending) and ``eigenvectors`` (columns), and ``f_inf``.

    Args:
        precision: ``d x d`` symmetric positive-definite :math:`\Sigma` (1 / knob²).
        f_inf: background :math:`f_\infty`.
        center: initial :math:`\mu` (``d``).
        peak: initial :math:`A > 0`.
        scale: initial :math:`s > 0`.
        n_eigen_scales: number of separately scaled top eigendirections, ``0 <= k <= d``.

    Raises:
        ValueError: bad shapes, non-finite values, non-positive ``peak``/``scale``.
    """

    def __init__(
        self,
        precision,
        f_inf: float,
        center,
        peak: float,
        scale: float = 1.0,
        n_eigen_scales: int = 0,
    ) -> None:
        super().__init__()
        P = torch.as_tensor(precision, dtype=DTYPE)
        if P.dim() != 2 or P.shape[0] != P.shape[1]:
            raise ValueError(f"precision must be d x d, got shape {tuple(P.shape)}")
        c = torch.as_tensor(center, dtype=DTYPE).reshape(-1)
        if c.shape[0] != P.shape[0]:
            raise ValueError(f"center has {c.shape[0]} entries, precision is {P.shape[0]}-D")
        if not (torch.isfinite(P).all() and torch.isfinite(c).all()):
            raise ValueError("precision and center must be finite")
        for name, v in (("peak", peak), ("scale", scale)):
            if not (float(v) > 0 and math.isfinite(float(v))):
                raise ValueError(f"{name} must be positive and finite, got {v}")
        if not math.isfinite(float(f_inf)):
            raise ValueError(f"f_inf must be finite, got {f_inf}")
        k = int(n_eigen_scales)
        if not 0 <= k <= P.shape[0]:
            raise ValueError(f"n_eigen_scales must lie in [0, {P.shape[0]}], got {n_eigen_scales}")
        evals, evecs = torch.linalg.eigh(P)
        if not evals[0] > 0:
            raise ValueError("precision must be positive definite")
        order = torch.argsort(evals, descending=True)
        self.register_buffer("precision", P.clone())
        self.register_buffer("eigenvalues", evals[order].clone())
        self.register_buffer("eigenvectors", evecs[:, order].clone())
        self.register_buffer("f_inf", torch.tensor(float(f_inf), dtype=DTYPE))
        self.center = torch.nn.Parameter(c.clone())
        self.log_peak = torch.nn.Parameter(torch.tensor(math.log(float(peak)), dtype=DTYPE))
        self.log_scale = torch.nn.Parameter(torch.tensor(math.log(float(scale)), dtype=DTYPE))
        self.log_eigen_scales = torch.nn.Parameter(torch.zeros(k, dtype=DTYPE))

    @classmethod
    def from_prior(cls, prior: PhysicsPrior, center=None, n_eigen_scales: int = 0) -> PhysicsMean:
        r"""The mean with the prior's :math:`\Sigma`, :math:`f_\infty`, :math:`A = f(x_0) -
        f_\infty`, :math:`s = 1` and :math:`\mu` = ``center`` (default ``prior.x0``)."""
        return cls(
            prior.precision,
            prior.f_inf,
            prior.x0 if center is None else center,
            prior.f_x0 - prior.f_inf,
            n_eigen_scales=n_eigen_scales,
        )

    @property
    def dim(self) -> int:
        return self.precision.shape[0]

    def quadratic(self, x: torch.Tensor) -> torch.Tensor:
        r"""The quadratic form, ``... x d`` -> ``...``.

        .. math:: q = 2 \sum_i s\, e^{a_i} \lambda_i \big(v_i^\top (\mathbf x - \mu)\big)^2
                    = 2 s\, (\mathbf x - \mu)^\top \Sigma (\mathbf x - \mu) \ \text{if } a = 0,

        with :math:`\Sigma = \sum_i \lambda_i v_i v_i^\top` (eigenvalues descending) and
        :math:`a_i` the ``log_eigen_scales`` (zero beyond the first ``n_eigen_scales``).
        """
        proj = (x - self.center) @ self.eigenvectors
        k = self.log_eigen_scales.shape[0]
        log_s = self.log_scale + torch.nn.functional.pad(self.log_eigen_scales, (0, self.dim - k))
        return 2.0 * (proj**2 * (self.eigenvalues * torch.exp(log_s))).sum(-1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        r"""``... x d`` knob settings -> ``...`` mean values."""
        return self.f_inf + torch.exp(self.log_peak) * torch.rsqrt(1.0 + self.quadratic(x))


def fit_physics_mean(
    mean: PhysicsMean,
    X: torch.Tensor,
    Y: torch.Tensor,
    covariance: torch.Tensor,
    *,
    center_prior: torch.Tensor,
    center_std: torch.Tensor,
    peak_prior: float,
    log_std: float = 1.0,
    max_iter: int = 50,
) -> float:
    r"""MAP fit of ``mean``'s parameters in place, the GP kernel held fixed.

    Minimizes the negative log posterior (up to constants)

    .. math::
        \tfrac12 \mathbf r^\top C^{-1} \mathbf r
        + \tfrac12 \big\|(\mu - \mu_0)/\tau\big\|^2
        + \frac{(\log A - \log A_0)^2 + (\log s)^2 + \|a\|^2}{2 \lambda^2},
        \qquad \mathbf r = \mathbf y - m(X),

    with :math:`C` = ``covariance`` (kernel matrix plus noise, ``n x n``), :math:`\mu_0` =
    ``center_prior``, :math:`\tau` = ``center_std``, :math:`A_0` = ``peak_prior`` and
    :math:`\lambda` = ``log_std``, by L-BFGS (strong Wolfe) warm-started from the current values.

    Args:
        mean: the :class:`PhysicsMean` to fit (modified in place).
        X: ``n x d`` settings. Y: ``n`` or ``n x 1`` readings.
        covariance: ``n x n`` positive-definite :math:`C`.
        center_prior: ``d`` prior centre :math:`\mu_0`. center_std: ``d`` (or scalar) :math:`\tau`.
        peak_prior: :math:`A_0 > 0`.
        log_std: :math:`\lambda > 0`.
        max_iter: L-BFGS iterations.

    Returns:
        The final objective value.

    If the optimization ends on a non-finite objective the parameters are restored to their
    starting values.

    Raises:
        ValueError: mismatched shapes, non-finite data or non-positive scales.
    """
    Y = Y.reshape(-1)
    n = Y.shape[0]
    if X.dim() != 2 or X.shape != (n, mean.dim):
        raise ValueError(f"X must be {n} x {mean.dim}, got {tuple(X.shape)}")
    if not (torch.isfinite(X).all() and torch.isfinite(Y).all()):
        raise ValueError("X and Y must be finite")
    if covariance.shape != (n, n):
        raise ValueError(f"covariance must be {n} x {n}, got {tuple(covariance.shape)}")
    if not (peak_prior > 0 and log_std > 0):
        raise ValueError("peak_prior and log_std must be positive")
    L = torch.linalg.cholesky(covariance)
    tau = torch.as_tensor(center_std, dtype=DTYPE).expand(mean.dim)
    log_a0 = math.log(float(peak_prior))
    params = [mean.center, mean.log_peak, mean.log_scale, mean.log_eigen_scales]
    for p in params:
        p.requires_grad_(True)
    opt = torch.optim.LBFGS(params, max_iter=int(max_iter), line_search_fn="strong_wolfe")

    def objective():
        r = (Y - mean(X)).unsqueeze(-1)
        w = torch.linalg.solve_triangular(L, r, upper=False)
        loss = 0.5 * (w**2).sum()
        loss = loss + 0.5 * (((mean.center - center_prior) / tau) ** 2).sum()
        logs = (mean.log_peak - log_a0) ** 2 + mean.log_scale**2 + (mean.log_eigen_scales**2).sum()
        return loss + logs / (2 * log_std**2)

    def closure():
        opt.zero_grad()
        loss = objective()
        loss.backward()
        return loss

    start = [p.detach().clone() for p in params]
    with torch.enable_grad():
        opt.step(closure)
    for p in params:
        p.requires_grad_(False)
    with torch.no_grad():
        loss = float(objective())
        if not math.isfinite(loss):  # a diverged line search: keep the warm start
            for p, p0 in zip(params, start, strict=True):
                p.copy_(p0)
            loss = float(objective())
    return loss
