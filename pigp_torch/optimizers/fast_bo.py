r"""Millisecond Bayesian-optimization steps for a FIXED kernel (the physics-informed GP).

:class:`~pigp_torch.optimizers.BayesOpt` rebuilds a BoTorch model from all data at every ask
(an :math:`O(n^3)` Cholesky) and maximizes the acquisition with autograd through GPyTorch. When
nothing of the kernel is fitted -- the PI-GP of Hanuka et al. -- all of that work can be kept
between steps. :class:`FastBayesOpt` is the same method (same trust box, acquisitions, options and
determinism rules) with its own exact posterior:

* the kernel :math:`k(\mathbf x, \mathbf x') = \sigma_f^2 \exp(-\tfrac12 (\mathbf x -
  \mathbf x')^\top P (\mathbf x - \mathbf x'))` is evaluated in whitened coordinates
  :math:`\mathbf z = \mathbf x L` (:math:`P = L L^\top`), where it is an isotropic RBF;
* the Cholesky factor :math:`C` of :math:`K + \sigma_n^2 I` grows by one row per tell
  (:math:`O(n^2)`), and so do :math:`A = (K + \sigma_n^2 I)^{-1}` (bordering / Schur complement)
  and :math:`\boldsymbol\alpha = A(\mathbf y - \mathbf m)`;
* posterior mean, variance and their gradients and Hessians are closed-form matrix products,
  batched over all starts of the acquisition search;
* the starts (the trust-box center, the last proposals, the best of a batch of random points in
  the box) climb together with a batched projected Newton method
  (:func:`maximize_in_unit_box`), or, for a callable prior mean or many knobs, as one stacked
  L-BFGS-B problem as BoTorch's ``gen_candidates_scipy`` does.

Why hand-written rather than BoTorch: a BoTorch ``SingleTaskGP`` cannot be grown by one row
(``condition_on_observations`` builds a new model and its caches each time, with the autograd
overhead of GPyTorch on every acquisition evaluation); an online step budget of tens of
milliseconds leaves no room for that. The posterior is checked against
:func:`~pigp_torch.models.physics_informed_gp` to 1e-9 and the proposals against
``optimize_acqf`` in the tests.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

import numpy as np
import scipy.linalg
import scipy.special
import torch
from gpytorch import settings as gpytorch_settings

from pigp_torch._lbfgsb import minimize_lbfgsb
from pigp_torch._utils import DTYPE, as_knob_tensor
from pigp_torch.kernels._base import precision_cholesky
from pigp_torch.optimizers.base import (
    AskTellOptimizer,
    check_search_options,
    check_ucb_options,
    trust_box,
)
from pigp_torch.optimizers.bayesopt import TRUST_CENTERS

#: Acquisitions of :class:`FastBayesOpt` (the names of :class:`BayesOpt`).
FAST_ACQUISITIONS = ("ucb", "ei", "logei")
#: Smallest noise variance, as GPyTorch's ``FixedNoiseGaussianLikelihood`` rounds up in float64
#: (so the posterior equals BoTorch's also for tiny noise, and the Gram stays invertible).
MIN_NOISE_VARIANCE = float(gpytorch_settings.min_fixed_noise.value(torch.float64))
#: Acquisition optimizers of :class:`FastBayesOpt` and their default ``options``: the batched
#: projected Newton method (:func:`maximize_in_unit_box`) or scipy's L-BFGS-B on the stacked starts
#: (BoTorch's ``gen_candidates_scipy`` scheme; needed for a callable prior mean, whose Hessian is
#: not available).
SOLVER_DEFAULTS = {
    "newton": {"maxiter": 50, "gtol": 1e-7, "ftol": 1e-12},
    "lbfgsb": {"maxiter": 200, "ftol": 2.220446049250313e-09, "gtol": 1e-5, "maxcor": 10},
}
#: ``method="auto"`` uses Newton up to this many knobs: its Hessian costs :math:`O(n^2 d)` per
#: start, so at many knobs L-BFGS-B is the cheaper search, while at few knobs Newton needs fewer
#: acquisition evaluations for the same or better values (``pigp bench bo`` measures both).
NEWTON_MAX_DIM = 32
#: Damping multipliers tried at once in each round of :func:`maximize_in_unit_box`.
DAMPING_TRIALS = np.array([1.0, 4.0, 16.0, 64.0])
#: Smallest posterior variance used in the acquisition (BoTorch's ``min_var``).
MIN_VARIANCE = 1e-12

_SQRT_HALF_PI = math.sqrt(math.pi / 2)
_LOG_SQRT_2PI = 0.5 * math.log(2 * math.pi)


def _log_h(z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    r""":math:`\log h(z)` and :math:`\Phi(z) / h(z)` for :math:`h(z) = \varphi(z) + z\Phi(z)`.

    :math:`h` is the expected improvement of a unit Gaussian; :math:`h' = \Phi`. For
    :math:`z \le -1` both are computed from the Mills ratio :math:`R(t) = \Phi(-t)/\varphi(t) =
    \sqrt{\pi/2}\,\mathrm{erfcx}(t/\sqrt2)`, :math:`h(-t) = \varphi(t)(1 - tR(t))`, and for
    :math:`t > 40` from the asymptotic series :math:`1 - tR(t) = t^{-2} - 3t^{-4} + 15t^{-6} -
    105t^{-8} + 945t^{-10}` (relative error < 1e-12), so LogEI stays finite far from the data.
    """
    z = np.asarray(z, dtype=np.float64)
    log_h = np.empty_like(z)
    ratio = np.empty_like(z)
    hi = z > -1.0
    zh = z[hi]
    h = np.exp(-0.5 * zh**2 - _LOG_SQRT_2PI) + zh * scipy.special.ndtr(zh)
    log_h[hi] = np.log(h)
    ratio[hi] = scipy.special.ndtr(zh) / h
    t = -z[~hi]
    mills = _SQRT_HALF_PI * scipy.special.erfcx(t / math.sqrt(2))
    inv2 = 1.0 / t**2
    series = inv2 * (1 - inv2 * (3 - inv2 * (15 - inv2 * (105 - 945 * inv2))))
    one_minus = np.where(t > 40.0, series, 1.0 - t * mills)
    log_h[~hi] = -0.5 * t**2 - _LOG_SQRT_2PI + np.log(one_minus)
    ratio[~hi] = mills / one_minus  # Phi(-t)/h(-t) = R(t) phi(t) / (phi(t) (1 - tR))
    return log_h, ratio


class IncrementalGP:
    r"""Exact GP posterior of a fixed full-precision RBF kernel, grown one observation at a time.

    .. math::
        y_i = g(\mathbf x_i) + \varepsilon_i, \quad g \sim \mathcal{GP}(m, k), \quad
        k(\mathbf x, \mathbf x') = \sigma_f^2 \exp\!\left(-\tfrac12 \lVert \mathbf z -
        \mathbf z' \rVert^2\right), \quad \mathbf z = \mathbf x L,\; P = L L^\top,

    :math:`\varepsilon_i \sim \mathcal N(0, \sigma_n^2)` with
    :math:`\sigma_n^2 \ge` :data:`MIN_NOISE_VARIANCE`. With :math:`G = K + \sigma_n^2 I = C C^\top`,
    :math:`A = G^{-1}` and :math:`\boldsymbol\alpha = A(\mathbf y - \mathbf m)`:

    .. math::
        \mu(\mathbf x) = m(\mathbf x) + \mathbf k^\top \boldsymbol\alpha, \qquad
        \sigma^2(\mathbf x) = \sigma_f^2 - \mathbf k^\top A \mathbf k,

    the posterior of the latent :math:`g` (no observation noise), as BoTorch's
    ``posterior(X)``. :meth:`add` borders :math:`C` with one row
    (:math:`\mathbf c = C^{-1}\mathbf k`, :math:`d = \sqrt{\kappa - \mathbf c^\top \mathbf c}`,
    :math:`\kappa = \sigma_f^2 + \sigma_n^2`), and :math:`A`, :math:`\boldsymbol\alpha` through the
    Schur complement :math:`s = d^2`, :math:`\mathbf b = A\mathbf k`:

    .. math::
        A' = \begin{pmatrix} A + \mathbf b \mathbf b^\top / s & -\mathbf b / s \\
        -\mathbf b^\top / s & 1/s \end{pmatrix}, \qquad
        \boldsymbol\alpha' = \begin{pmatrix} \boldsymbol\alpha - e\,\mathbf b \\ e \end{pmatrix},
        \quad e = \frac{r_{n+1} - \mathbf k^\top \boldsymbol\alpha}{s},

    all :math:`O(n^2)`. Gradients (:meth:`predict`) use
    :math:`\partial k_i / \partial \mathbf z = -k_i (\mathbf z - \mathbf z_i)`.

    Storage grows by doubling, so a tell copies nothing in the common case. Arrays are numpy
    float64 (the hot path is called by scipy's L-BFGS-B, where torch's per-call overhead would
    dominate at these sizes).

    Args:
        precision: ``d x d`` symmetric positive-definite :math:`P` (1 / knob²).
        amplitude: :math:`\sigma_f^2 > 0`.
        noise: :math:`\sigma_n \ge 0` (a standard deviation).
        mean: constant prior mean (float) or a callable ``(X: N x d tensor) -> N tensor``,
            differentiable with torch autograd (e.g. a gpytorch ``Mean``).
    """

    def __init__(self, precision, amplitude: float, noise: float, mean=0.0) -> None:
        self.L = precision_cholesky(precision).numpy()
        self.dim = self.L.shape[0]
        amplitude = float(amplitude)
        if not (math.isfinite(amplitude) and amplitude > 0):
            raise ValueError(f"amplitude must be positive and finite, got {amplitude}")
        noise = float(noise)
        if not (math.isfinite(noise) and noise >= 0):
            raise ValueError(f"noise must be a finite standard deviation >= 0, got {noise}")
        self.amplitude = amplitude
        self.noise_variance = max(noise**2, MIN_NOISE_VARIANCE)
        self.n = 0
        self._cap = 0
        self._z_ref: np.ndarray | None = None
        self._set_mean(mean)
        self._grow(16)

    # -- mean -----------------------------------------------------------------------------------
    def _set_mean(self, mean) -> None:
        if callable(mean):
            self.mean_fn: Callable | None = mean
            self.mean_const = 0.0
        else:
            try:
                value = float(mean)
            except (TypeError, ValueError):
                raise ValueError(f"mean must be a float or a callable, got {mean!r}") from None
            if not math.isfinite(value):
                raise ValueError(f"mean must be finite, got {value}")
            self.mean_fn = None
            self.mean_const = value

    def prior_mean(self, X: np.ndarray, grad: bool = False):
        r""":math:`m(\mathbf x)` at ``X: N x d`` (knob units) and, with ``grad``, ``N x d``
        :math:`\nabla_{\mathbf x} m`."""
        if self.mean_fn is None:
            m = np.full(X.shape[0], self.mean_const)
            return (m, np.zeros_like(X)) if grad else m
        Xt = torch.from_numpy(np.ascontiguousarray(X)).requires_grad_(grad)
        with torch.enable_grad() if grad else torch.no_grad():
            m = self.mean_fn(Xt).reshape(-1)
            if m.shape[0] != X.shape[0]:
                raise ValueError(f"mean must return one value per row, got {tuple(m.shape)}")
            if not grad:
                return m.detach().numpy().astype(np.float64)
            (g,) = torch.autograd.grad(m.sum(), Xt)
        return m.detach().numpy().astype(np.float64), g.numpy()

    def set_mean(self, mean) -> None:
        r"""Replace the prior mean; recomputes :math:`\boldsymbol\alpha = A(\mathbf y -
        \mathbf m)` in :math:`O(n^2)` (the kernel part, :math:`C` and :math:`A`, is kept)."""
        self._set_mean(mean)
        n = self.n
        if n:
            self._r[:n] = self._y[:n] - self.prior_mean(self._X[:n])
            self._alpha[:n] = self._A[:n, :n] @ self._r[:n]

    # -- storage --------------------------------------------------------------------------------
    def _grow(self, cap: int) -> None:
        """Reallocate the storage for ``cap`` observations, keeping the first ``n``."""
        n, d = self.n, self.dim
        shapes = {
            "_C": (cap, cap),
            "_A": (cap, cap),
            "_Z": (cap, d),
            "_X": (cap, d),
            "_y": (cap,),
            "_r": (cap,),
            "_alpha": (cap,),
            "_sqn": (cap,),
        }
        for name, shape in shapes.items():
            new = np.zeros(shape)
            old = self.__dict__.get(name)
            if old is not None and n:
                index = (slice(0, n),) * (2 if name in ("_C", "_A") else 1)
                new[index] = old[index]
            self.__dict__[name] = new
        self._cap = cap

    # -- data -----------------------------------------------------------------------------------
    def whiten(self, X: np.ndarray) -> np.ndarray:
        r"""Whitened, centered coordinates :math:`\mathbf x L - \mathbf z_\mathrm{ref}` (the
        first point added is the reference, which keeps squared distances accurate)."""
        Z = X @ self.L
        return Z if self._z_ref is None else Z - self._z_ref

    def add(self, x, y: float) -> None:
        """Condition on one more observation ``y`` at ``x`` (``d``); :math:`O(n^2)`."""
        x = np.asarray(x, dtype=np.float64).reshape(-1)
        if x.shape[0] != self.dim:
            raise ValueError(f"point has {x.shape[0]} entries, the GP has {self.dim} inputs")
        n = self.n
        if n == self._cap:
            self._grow(2 * self._cap)
        if self._z_ref is None:
            self._z_ref = x @ self.L
        z = self.whiten(x[None])[0]
        r = float(y) - float(self.prior_mean(x[None])[0])
        kappa = self.amplitude + self.noise_variance
        if n:
            Z, sqn = self._Z[:n], self._sqn[:n]
            sq = np.maximum(sqn + z @ z - 2.0 * (Z @ z), 0.0)
            k = self.amplitude * np.exp(-0.5 * sq)
            C = self._C[:n, :n]
            c = scipy.linalg.solve_triangular(C, k, lower=True, check_finite=False)
            s = kappa - c @ c
            if not s > 0:
                raise ValueError(
                    "the kernel matrix lost positive definiteness (a repeated point with "
                    f"noise variance {self.noise_variance:.3g}?)"
                )
            A = self._A[:n, :n]
            b = A @ k
            e = (r - k @ self._alpha[:n]) / s
            A += np.outer(b, b / s)
            self._A[n, :n] = self._A[:n, n] = -b / s
            self._alpha[:n] -= e * b
            self._C[n, :n] = c
        else:
            s = kappa
            e = r / s
        self._C[n, n] = math.sqrt(s)
        self._A[n, n] = 1.0 / s
        self._alpha[n] = e
        self._Z[n], self._X[n], self._sqn[n] = z, x, z @ z
        self._y[n], self._r[n] = float(y), r
        self.n = n + 1

    @property
    def cholesky(self) -> np.ndarray:
        """``n x n`` lower Cholesky factor :math:`C` of :math:`K + \\sigma_n^2 I` (a copy)."""
        return self._C[: self.n, : self.n].copy()

    @property
    def inverse(self) -> np.ndarray:
        """``n x n`` :math:`A = (K + \\sigma_n^2 I)^{-1}` (a copy)."""
        return self._A[: self.n, : self.n].copy()

    @property
    def alpha(self) -> np.ndarray:
        r""":math:`\boldsymbol\alpha = A(\mathbf y - \mathbf m)` (a copy)."""
        return self._alpha[: self.n].copy()

    def train_mean(self) -> np.ndarray:
        r"""Posterior mean at the training points, :math:`\mathbf y - \sigma_n^2
        \boldsymbol\alpha` (since :math:`K\boldsymbol\alpha = \mathbf r - \sigma_n^2
        \boldsymbol\alpha`), :math:`O(n)`."""
        return self._y[: self.n] - self.noise_variance * self._alpha[: self.n]

    # -- prediction -----------------------------------------------------------------------------
    def predict(self, X: np.ndarray, order: int = 0):
        r"""Posterior mean and variance of :math:`g` at ``X: N x d`` (knob units), with
        derivatives up to ``order`` (0, 1 or 2) with respect to :math:`\mathbf x`.

        With :math:`\mathbf D_i = \mathbf z - \mathbf z_i`, :math:`\mathbf b = A\mathbf k`
        and :math:`J = \partial\mathbf k/\partial\mathbf z` (rows :math:`-k_i\mathbf D_i^\top`),
        in whitened coordinates:

        .. math::
            \nabla\mu = -\sum_i \alpha_i k_i \mathbf D_i, \quad
            \nabla^2\mu = \sum_i \alpha_i k_i (\mathbf D_i \mathbf D_i^\top - I), \quad
            \nabla\sigma^2 = 2\sum_i b_i k_i \mathbf D_i, \quad
            \nabla^2\sigma^2 = -2\Big[J^\top A J + \sum_i b_i k_i (\mathbf D_i
            \mathbf D_i^\top - I)\Big],

        mapped to knob units by :math:`\nabla_x = L\nabla_z`, :math:`\nabla^2_x = L\nabla^2_z
        L^\top`. The Hessian costs :math:`O(N n^2 d)`.

        Returns:
            ``(mu, var)`` (``N`` each), plus ``(dmu, dvar)`` (``N x d``) for ``order >= 1``,
            plus ``(hmu, hvar)`` (``N x d x d``) for ``order == 2``.

        Raises:
            ValueError: ``order == 2`` with a callable prior mean (its Hessian is not available).
        """
        n = self.n
        if n == 0:
            raise RuntimeError("no observations yet")
        if order == 2 and self.mean_fn is not None:
            raise ValueError("second derivatives need a constant prior mean")
        Zs = self.whiten(X)
        Z, A, alpha = self._Z[:n], self._A[:n, :n], self._alpha[:n]
        sq = np.maximum((Zs * Zs).sum(1)[:, None] + self._sqn[:n] - 2.0 * (Zs @ Z.T), 0.0)
        K = self.amplitude * np.exp(-0.5 * sq)  # N x n
        B = K @ A  # rows: (A k)^T
        var = self.amplitude - (B * K).sum(1)
        if order == 0:
            return self.prior_mean(X) + K @ alpha, var
        m, dm = self.prior_mean(X, grad=True)
        mu = m + K @ alpha
        Ka = K * alpha
        dmu_z = Ka @ Z - Ka.sum(1)[:, None] * Zs
        KB = K * B
        dvar_z = 2.0 * (KB.sum(1)[:, None] * Zs - KB @ Z)
        L = self.L
        out = (mu, var, dm + dmu_z @ L.T, dvar_z @ L.T)
        if order == 1:
            return out
        D = Zs[:, None, :] - Z[None]  # N x n x d
        KD = K[:, :, None] * D  # = -J
        # one batched product for both: KD^T [alpha D, A KD + b D]  (N x d x 2d)
        right = np.concatenate([alpha[None, :, None] * D, np.matmul(A, KD) + B[:, :, None] * D], 2)
        prod = np.matmul(KD.transpose(0, 2, 1), right)
        d = self.dim
        hmu_z, hvar_z = prod[:, :, :d], -2.0 * prod[:, :, d:]
        hmu_z[:, range(d), range(d)] -= Ka.sum(1)[:, None]
        hvar_z[:, range(d), range(d)] += 2.0 * KB.sum(1)[:, None]
        return (*out, L @ hmu_z @ L.T, L @ hvar_z @ L.T)


def maximize_in_unit_box(
    fun: Callable[..., tuple],
    U0: np.ndarray,
    *,
    maxiter: int = 50,
    gtol: float = 1e-7,
    ftol: float = 1e-12,
    max_trials: int = 40,
) -> tuple[np.ndarray, np.ndarray, dict]:
    r"""Batched projected Levenberg-Marquardt-Newton ascent of independent starts in
    :math:`[0,1]^d`.

    Each row of ``U0`` is one start; all rows move at once (one call of ``fun`` per round for all
    of them) but each has its own step and damping. Per start, with gradient :math:`\mathbf g`,
    Hessian :math:`H` and the binding set :math:`B = \{j: u_j \le \epsilon, g_j < 0\} \cup
    \{j: u_j \ge 1 - \epsilon, g_j > 0\}` (Bertsekas' projected Newton, :math:`\epsilon` = the
    projected-gradient norm, at most 1e-3), the step on the free coordinates
    :math:`F` is

    .. math:: \mathbf p_F = V (\max(\Lambda, 0) + \lambda I)^{-1} V^\top \mathbf g_F, \qquad
              -H_{FF} = V \Lambda V^\top,

    :math:`\mathbf p_B = 0`, and the trial point is :math:`\mathrm{clip}(\mathbf u +
    \mathbf p, 0, 1)`. Along concave directions this is a damped Newton step; along convex
    ones (at a data point the variance has a minimum) the damping alone sets the step, which
    grows while steps succeed, so a start escapes a convex region quickly. The damping
    :math:`\lambda` is adapted from the ratio :math:`\rho` of the actual to the predicted gain
    of the quadratic model (Levenberg-Marquardt, like a trust region): a trial with
    :math:`\rho < 10^{-4}` is rejected; an accepted one divides
    :math:`\lambda` by 4 when :math:`\rho > 0.75` and doubles it when :math:`\rho < 0.25`.
    Each round tries the dampings :math:`\lambda \cdot` :data:`DAMPING_TRIALS` in one batched
    evaluation and keeps the accepted trial of largest gain (a rejection of all of them
    multiplies :math:`\lambda` by 256).
    Near the optimum :math:`\lambda \to 0` (pure Newton, quadratic convergence). A start stops
    when its projected gradient :math:`\max_j |\mathrm{clip}(u_j + g_j, 0, 1) - u_j|` is below
    ``gtol``, when a step gains less than ``ftol`` :math:`(1 + |f|)`, or after ``max_trials``
    rejected trials in a row.

    Hand-written because scipy's L-BFGS-B (the starts stacked into one problem) needs 100-200
    iterations here and spends most of its time in per-call Python overhead; Newton steps with the
    closed-form Hessian converge in a few iterations, for all starts at once.

    Args:
        fun: ``fun(U: k x d, order)`` returning values (``order=0``) or ``(values, grads,
            hessians)`` (``order=2``) in unit-cube coordinates.
        U0: ``k x d`` starts (clipped into the cube).
        maxiter: accepted steps at most per start.
        gtol: projected-gradient tolerance.
        ftol: relative gain tolerance.
        max_trials: rejected trials in a row before a start gives up.

    Returns:
        ``(U, f, info)``: final points, their values and ``{"iterations", "evaluations"}``
        (accepted steps of the slowest start, batched calls of ``fun``).
    """
    U = np.clip(np.array(U0, dtype=np.float64), 0.0, 1.0)
    k, d = U.shape
    f, g, H = fun(U, 2)
    n_evals = 1
    steps = np.zeros(k, dtype=int)
    fails = np.zeros(k, dtype=int)
    damping = np.zeros(k)
    scale = np.ones(k)
    active = np.ones(k, dtype=bool)
    need_eig = np.ones(k, dtype=bool)
    lam = np.ones((k, d))
    V = np.zeros((k, d, d))
    Vg = np.zeros((k, d))
    free = np.ones((k, d), dtype=bool)
    diag = np.arange(d)
    for _ in range(maxiter * (max_trials + 1)):
        pg = np.clip(U + g, 0.0, 1.0) - U
        active &= (np.abs(pg).max(1) > gtol) & (steps < maxiter) & (fails < max_trials)
        if not active.any():
            break
        idx = np.flatnonzero(active)
        # eigen-decompose the reduced Hessian once per accepted step
        e = idx[need_eig[idx]]
        if e.size:
            # epsilon-binding set (Bertsekas): within eps of a bound and pushing against it
            eps = np.minimum(1e-3, np.abs(pg[e]).max(1))[:, None]
            fr = ~(((U[e] <= eps) & (g[e] < 0.0)) | ((U[e] >= 1.0 - eps) & (g[e] > 0.0)))
            M = -H[e] * (fr[:, :, None] & fr[:, None, :])
            M[:, diag, diag] += ~fr
            w, Ve = np.linalg.eigh(M)
            lam[e], V[e], free[e] = w, Ve, fr
            Vg[e] = np.einsum("kji,kj->ki", Ve, g[e] * fr)
            scale[e] = np.abs(w).max(1) + 1e-300
            damping[e] = np.where(steps[e] == 0, 1e-3 * scale[e], damping[e])
            need_eig[e] = False
        # concave directions: damped Newton; convex ones (lam < 0): the damping alone. Several
        # dampings are tried at once (one batched evaluation instead of a round per rejection).
        a, m = idx.size, DAMPING_TRIALS.size
        denom = (
            np.maximum(lam[idx], 0.0)[:, None, :]
            + damping[idx, None, None] * DAMPING_TRIALS[None, :, None]
        )
        p = np.einsum("kij,kmj->kmi", V[idx], Vg[idx][:, None, :] / denom) * free[idx][:, None]
        trial = np.clip(U[idx][:, None, :] + p, 0.0, 1.0)
        ft = fun(trial.reshape(a * m, d), 0).reshape(a, m)
        n_evals += 1
        step = trial - U[idx][:, None, :]
        quad = np.einsum("kmi,kij,kmj->km", step, H[idx], step)
        predicted = np.einsum("ki,kmi->km", g[idx], step) + 0.5 * quad
        actual = ft - f[idx][:, None]
        rho = np.where(predicted > 0, actual / np.where(predicted > 0, predicted, 1.0), -1.0)
        okm = (actual > 0) & (rho > 1e-4)
        best = np.argmax(np.where(okm, actual, -np.inf), axis=1)
        ok = okm[np.arange(a), best]
        acc, rej = idx[ok], idx[~ok]
        damping[rej] = np.maximum(4.0 * DAMPING_TRIALS[-1] * damping[rej], 1e-8 * scale[rej])
        fails[rej] += 1
        rho = rho[np.arange(a), best]
        actual = actual[np.arange(a), best]
        trial = trial[np.arange(a), best]
        ft = ft[np.arange(a), best]
        damping[acc] *= DAMPING_TRIALS[best[ok]]
        if acc.size:
            r = rho[ok]
            lower = 1e-12 * scale[acc]
            damping[acc] = np.where(r > 0.75, np.maximum(damping[acc] / 4, lower), damping[acc])
            damping[acc] = np.where(r < 0.25, 2.0 * damping[acc], damping[acc])
            small_gain = actual[ok] <= ftol * (1.0 + np.abs(f[acc]))
            U[acc] = trial[ok]
            fails[acc] = 0
            steps[acc] += 1
            active[acc[small_gain]] = False
            go = acc[~small_gain]
            if go.size:
                f[go], g[go], H[go] = fun(U[go], 2)
                n_evals += 1
                need_eig[go] = True
            f[acc[small_gain]] = ft[ok][small_gain]
    return U, f, {"iterations": int(steps.max(initial=0)), "evaluations": n_evals}


def _maximize_lbfgsb(fun, U0: np.ndarray, options: dict):
    """All starts as one L-BFGS-B problem on the sum of their values (BoTorch's scheme)."""
    k, d = U0.shape
    count = {"n": 0}

    def neg_total(uflat: np.ndarray) -> tuple[float, np.ndarray]:
        value, g = fun(uflat.reshape(k, d), 1)
        count["n"] += 1
        return -float(value.sum()), -g.reshape(-1)

    res = minimize_lbfgsb(neg_total, U0.reshape(-1), bounds=[(0.0, 1.0)] * (k * d), **options)
    U = np.clip(res.x.reshape(k, d), 0.0, 1.0)
    return U, fun(U, 0), {"iterations": int(res.nit), "evaluations": count["n"] + 1}


class FastBayesOpt(AskTellOptimizer):
    r"""Bayesian optimization with a fixed full-precision RBF kernel in milliseconds per step.

    Same method as :class:`~pigp_torch.optimizers.BayesOpt` with the model
    :func:`~pigp_torch.models.physics_informed_gp` (kernel ``"rbf"``): the acquisition is
    maximized inside the trust box

    .. math:: \max\!\big(\ell,\; c - s\,\tfrac{h - \ell}{2}\big) \le x \le
              \min\!\big(h,\; c + s\,\tfrac{h - \ell}{2}\big)

    around the center :math:`c` (``"best_observed"``: the best noisy reading, first one on ties;
    ``"best_mean"``: the told point of highest posterior mean), clamped into the bounds; the
    proposal never leaves the bounds or the box. Acquisitions (internal, maximized sign):
    ``"ucb"`` :math:`\mu + \sqrt\beta\,\sigma`, ``"ei"`` :math:`\sigma h(z)`,
    ``"logei"`` :math:`\log(\sigma h(z))` with :math:`z = (\mu - y^*)/\sigma`,
    :math:`h(z) = \varphi(z) + z\Phi(z)` and :math:`y^*` the best observed value -- BoTorch's
    ``UpperConfidenceBound``, ``ExpectedImprovement`` and ``LogExpectedImprovement``.

    **Model.** The posterior is :class:`IncrementalGP` (exact, updated in :math:`O(n^2)` per
    :meth:`tell`). With ``maximize=False`` the GP sees :math:`-y` and the prior mean is negated
    with it: ``mean`` is always given in the objective's own units.

    **Acquisition search.** In the unit cube of the trust box: ``raw_samples`` uniform random
    points are scored in one batch; the ``num_restarts`` best of them, the box center and the last
    ``n_previous`` proposals (clipped into the box; duplicates dropped) are the starts of the
    batched projected Newton method :func:`maximize_in_unit_box` (closed-form Hessians) or of one
    stacked L-BFGS-B problem (closed-form gradients), see ``method``; the best point among the
    optimized starts and the raw samples is proposed.

    **Determinism.** The random points come from ``numpy.random.default_rng(seed + n_told)``; no
    global RNG is used.

    After each ask, ``last_info`` holds ``acq_value``, ``center``, ``trust_lower``,
    ``trust_upper``, ``fit_time_s`` (time of the last :meth:`tell`'s model update),
    ``acq_time_s``, ``n_train``, ``n_starts``, ``n_evals`` (batched acquisition evaluations),
    ``iterations`` (accepted steps of the slowest start, or L-BFGS-B iterations) and ``solver``.

    Args:
        bounds: ``2 x d`` knob bounds.
        precision: ``d x d`` kernel precision :math:`P` (1 / knob²).
        amplitude: kernel variance :math:`\sigma_f^2`.
        noise: measurement noise standard deviation :math:`\sigma_n` (variance floored at
            :data:`MIN_NOISE_VARIANCE`, as GPyTorch does).
        mean: prior mean in objective units: a float or a differentiable callable
            ``(X: N x d) -> N`` (e.g. a gpytorch ``Mean``); change it later with
            :meth:`set_mean`.
        acquisition: ``"ucb"``, ``"ei"`` or ``"logei"``.
        beta: UCB trade-off :math:`\beta \ge 0` (``4``: the authors' :math:`\mu + 2\sigma`).
        step_limit: trust-box half-width as a fraction of each knob's half-range, or ``None``.
        trust_center: ``"best_observed"`` or ``"best_mean"``.
        maximize: maximize (default) or minimize the objective.
        num_restarts: best random points kept as starts (>= 0). With 10 the search found an
            acquisition value at least as high as ``optimize_acqf``'s in 20 of 24 states of
            benchmark runs (4 restarts: 16 of 24).
        raw_samples: random points scored to pick them (>= ``num_restarts``).
        n_previous: earlier proposals used as extra starts (>= 0).
        seed: base seed of the per-ask random points.
        method: ``"newton"`` (:func:`maximize_in_unit_box`), ``"lbfgsb"`` (scipy, stacked
            starts) or ``"auto"`` (Newton unless the prior mean is a callable or there are more
            than :data:`NEWTON_MAX_DIM` knobs).
        options: solver options over :data:`SOLVER_DEFAULTS` of the method.
    """

    name = "fast-bo"

    def __init__(
        self,
        bounds,
        precision,
        *,
        amplitude: float,
        noise: float,
        mean=0.0,
        acquisition: str = "ucb",
        beta: float = 4.0,
        step_limit: float | None = 0.1,
        trust_center: str = "best_observed",
        maximize: bool = True,
        num_restarts: int = 10,
        raw_samples: int = 256,
        n_previous: int = 2,
        seed: int = 0,
        method: str = "auto",
        options: dict | None = None,
    ) -> None:
        super().__init__(bounds, maximize=maximize)
        acquisition = str(acquisition).lower()
        if acquisition not in FAST_ACQUISITIONS:
            raise ValueError(f"acquisition must be one of {FAST_ACQUISITIONS}, got {acquisition!r}")
        check_ucb_options(beta, step_limit)
        check_search_options(trust_center, TRUST_CENTERS, num_restarts, raw_samples, 0)
        if int(n_previous) < 0:
            raise ValueError(f"n_previous must be >= 0, got {n_previous}")
        if method not in ("auto", *SOLVER_DEFAULTS):
            raise ValueError(f"method must be 'auto', 'newton' or 'lbfgsb', got {method!r}")
        if method == "newton" and callable(mean):
            raise ValueError("method='newton' needs a constant prior mean; use 'lbfgsb' or 'auto'")
        self.method = method
        self.options = dict(options or {})
        known = set().union(*SOLVER_DEFAULTS.values()) if method == "auto" else None
        known = known or set(SOLVER_DEFAULTS[method])
        unknown = sorted(set(self.options) - known)
        if unknown:
            raise ValueError(
                f"unknown options {unknown} for method {method!r}; known: {sorted(known)}"
            )
        self.sign = 1.0 if self.maximize else -1.0
        self.gp = IncrementalGP(precision, amplitude, noise, self._signed_mean(mean))
        if self.gp.dim != self.dim:
            raise ValueError(f"precision is {self.gp.dim} x {self.gp.dim}, bounds have {self.dim}")
        self.acquisition = acquisition
        self.beta = float(beta)
        self.step_limit = None if step_limit is None else float(step_limit)
        self.trust_center = trust_center
        self.num_restarts = int(num_restarts)
        self.raw_samples = int(raw_samples)
        self.n_previous = int(n_previous)
        self.seed = int(seed)
        self.proposals: list[torch.Tensor] = []
        self.last_info: dict = {}
        self._tell_time = 0.0
        self._best_internal = -math.inf

    @classmethod
    def from_prior(cls, bounds, prior, *, mean="f_inf", **options) -> FastBayesOpt:
        r"""The PI-GP optimizer of a :class:`~pigp_torch.prior.PhysicsPrior`: precision
        :math:`\Sigma`, amplitude :math:`\sigma_f^2` and noise :math:`\sigma_n` of the prior.

        Args:
            bounds: ``2 x d`` knob bounds.
            prior: the physics prior.
            mean: ``"f_inf"`` (the paper), ``"zero"``, a float or a callable (objective units).
            **options: further :class:`FastBayesOpt` options.
        """
        from pigp_torch.prior import PhysicsPrior

        if not isinstance(prior, PhysicsPrior):
            raise ValueError(f"prior must be a PhysicsPrior, got {type(prior).__name__}")
        if isinstance(mean, str):
            if mean not in ("f_inf", "zero"):
                raise ValueError(
                    f'mean must be "f_inf", "zero", a float or a callable, got {mean!r}'
                )
            mean = prior.f_inf if mean == "f_inf" else 0.0
        return cls(
            bounds,
            prior.precision,
            amplitude=prior.amplitude,
            noise=prior.noise,
            mean=mean,
            **options,
        )

    def _signed_mean(self, mean):
        if self.maximize:
            return mean
        if callable(mean):
            return lambda X: -mean(X)
        return -float(mean)

    def set_mean(self, mean) -> None:
        """Replace the prior mean (objective units); :math:`O(n^2)`, the factor is kept."""
        if self.method == "newton" and callable(mean):
            raise ValueError("method='newton' needs a constant prior mean; use 'lbfgsb' or 'auto'")
        self.gp.set_mean(self._signed_mean(mean))

    def _solver(self) -> str:
        if self.method != "auto":
            return self.method
        if self.gp.mean_fn is not None or self.dim > NEWTON_MAX_DIM:
            return "lbfgsb"
        return "newton"

    # -- data -----------------------------------------------------------------------------------
    def tell(self, x, y: float) -> None:
        """Record one measurement and condition the GP on it (:math:`O(n^2)`)."""
        super().tell(x, y)
        t0 = time.perf_counter()
        yi = self.sign * self.Y[-1]
        try:
            self.gp.add(self.X[-1].numpy(), yi)
        except Exception:  # keep the history and the GP consistent
            self.X.pop()
            self.Y.pop()
            raise
        self._best_internal = max(self._best_internal, yi)
        self._tell_time = time.perf_counter() - t0

    def trust_box(self, center: torch.Tensor) -> torch.Tensor:
        r"""The ``2 x d`` search box around ``center`` (``d``), as :meth:`BayesOpt.trust_box`."""
        return trust_box(self.bounds, center, self.step_limit)

    def _center(self) -> torch.Tensor:
        if self.trust_center == "best_observed":
            y = self.sign * torch.tensor(self.Y, dtype=DTYPE)
            return self.X[int(y.argmax())]
        return self.X[int(np.argmax(self.gp.train_mean()))]

    # -- posterior and acquisition -------------------------------------------------------------
    def posterior(self, X) -> tuple[torch.Tensor, torch.Tensor]:
        r"""Posterior mean and variance of the latent objective at ``X`` (``N x d`` or ``d``), in
        the objective's own sign (the mean is negated back when minimizing)."""
        X, _ = as_knob_tensor(X, self.dim)
        mu, var = self.gp.predict(X.numpy())
        return self.sign * torch.from_numpy(mu), torch.from_numpy(var)

    def _acq(self, X: np.ndarray, order: int = 0):
        r"""Acquisition (internal sign) at ``X: N x d`` with derivatives up to ``order``.

        With :math:`\sigma = \sqrt{\max(\sigma^2, 10^{-12})}`,
        :math:`\nabla\sigma = \nabla\sigma^2 / 2\sigma`,
        :math:`\nabla^2\sigma = \nabla^2\sigma^2 / 2\sigma - \nabla\sigma^2
        \nabla\sigma^{2\top} / 4\sigma^3`, :math:`\mathbf w = \nabla\mu - z\nabla\sigma`
        (so :math:`\nabla z = \mathbf w / \sigma`) and :math:`r = \Phi(z)/h(z)`:

        * UCB: :math:`\nabla = \nabla\mu + \sqrt\beta\nabla\sigma`, same for the Hessian;
        * EI: :math:`\nabla = \Phi\nabla\mu + \varphi\nabla\sigma`,
          :math:`\nabla^2 = \Phi\nabla^2\mu + \varphi\nabla^2\sigma +
          (\varphi/\sigma)\mathbf w\mathbf w^\top`;
        * LogEI: :math:`\nabla = \nabla\sigma/\sigma + r\nabla z`,
          :math:`\nabla^2 = \nabla^2\sigma/\sigma - \nabla\sigma\nabla\sigma^\top/\sigma^2
          + r\nabla^2 z + (1 - zr - r^2)\nabla z\nabla z^\top` with
          :math:`\nabla^2 z = (\nabla^2\mu - z\nabla^2\sigma)/\sigma - (\nabla\sigma
          \nabla z^\top + \nabla z\nabla\sigma^\top)/\sigma`.

        Returns:
            ``value`` (``N``), or ``(value, grad)`` (``N x d``), or ``(value, grad, hess)``
            (``N x d x d``), in knob units.
        """
        out = self.gp.predict(X, order)
        mu, var = out[0], out[1]
        small = var < MIN_VARIANCE
        sigma = np.sqrt(np.where(small, MIN_VARIANCE, var))
        if order >= 1:
            inv2s = np.where(small, 0.0, 0.5 / sigma)
            dmu, dsig = out[2], inv2s[:, None] * out[3]
        if order == 2:
            hmu = out[4]
            hsig = inv2s[:, None, None] * out[5] - np.einsum(
                "N,Ni,Nj->Nij", np.where(small, 0.0, 1.0 / sigma), dsig, dsig
            )
        if self.acquisition == "ucb":
            sb = math.sqrt(self.beta)
            value = mu + sb * sigma
            if order == 0:
                return value
            if order == 1:
                return value, dmu + sb * dsig
            return value, dmu + sb * dsig, hmu + sb * hsig
        z = (mu - self._best_internal) / sigma
        if self.acquisition == "ei":
            pdf = np.exp(-0.5 * z**2 - _LOG_SQRT_2PI)
            cdf = scipy.special.ndtr(z)
            value = sigma * (pdf + z * cdf)
            if order == 0:
                return value
            grad = cdf[:, None] * dmu + pdf[:, None] * dsig
            if order == 1:
                return value, grad
            w = dmu - z[:, None] * dsig
            hess = (
                cdf[:, None, None] * hmu
                + pdf[:, None, None] * hsig
                + np.einsum("N,Ni,Nj->Nij", pdf / sigma, w, w)
            )
            return value, grad, hess
        log_h, ratio = _log_h(z)
        value = np.log(sigma) + log_h
        if order == 0:
            return value
        dz = (dmu - z[:, None] * dsig) / sigma[:, None]
        grad = dsig / sigma[:, None] + ratio[:, None] * dz
        if order == 1:
            return value, grad
        s3 = sigma[:, None, None]
        outer = np.einsum("Ni,Nj->Nij", dsig, dz)
        hz = (hmu - z[:, None, None] * hsig) / s3 - (outer + outer.transpose(0, 2, 1)) / s3
        hess = (
            hsig / s3
            - np.einsum("Ni,Nj->Nij", dsig, dsig) / s3**2
            + ratio[:, None, None] * hz
            + np.einsum("N,Ni,Nj->Nij", 1.0 - z * ratio - ratio**2, dz, dz)
        )
        return value, grad, hess

    def _acq_unit(self, U: np.ndarray, order: int, lo: np.ndarray, width: np.ndarray):
        """:meth:`_acq` in the unit cube of a box: ``x = lo + U * width``."""
        out = self._acq(lo + U * width, order)
        if order == 0:
            return out
        if order == 1:
            return out[0], out[1] * width
        return out[0], out[1] * width, out[2] * width[:, None] * width[None, :]

    def acquisition_value(self, X, *, order: int = 0):
        r"""The acquisition (internal, maximized sign) at knob settings ``X`` (``N x d``).

        Returns:
            ``N`` values; with ``order=1`` also the ``N x d`` gradients, with ``order=2`` also
            the ``N x d x d`` Hessians (knob units), as a tuple.
        """
        if order not in (0, 1, 2):
            raise ValueError(f"order must be 0, 1 or 2, got {order}")
        X, _ = as_knob_tensor(X, self.dim)
        if not self.Y:
            raise RuntimeError("no measurements yet: tell() the start point first")
        out = self._acq(X.numpy(), order)
        if order == 0:
            return torch.from_numpy(out)
        return tuple(torch.from_numpy(o) for o in out)

    # -- ask ------------------------------------------------------------------------------------
    def ask(self) -> torch.Tensor:
        r"""Maximize the acquisition in the trust box; returns ``d`` (see the class docstring)."""
        if not self.Y:
            raise RuntimeError("no measurements yet: tell() the start point first")
        t0 = time.perf_counter()
        d = self.dim
        center = self._center()
        box = self.trust_box(center)
        lo, width = box[0].numpy(), (box[1] - box[0]).numpy()

        def to_unit(x: torch.Tensor) -> np.ndarray:
            return np.clip((x.numpy() - lo) / width, 0.0, 1.0)

        starts = [to_unit(center)[None]]
        previous = self.proposals[max(0, len(self.proposals) - self.n_previous) :]
        starts += [to_unit(p)[None] for p in previous[::-1]]
        raw = np.empty((0, d))
        raw_values = np.empty(0)
        n_evals = 0
        if self.raw_samples:
            # uniform points from a fresh seeded generator: a scrambled SobolEngine costs ~1 ms
            raw = np.random.default_rng(self.seed + self.n_told).random((self.raw_samples, d))
            raw_values = self._acq(lo + raw * width)
            n_evals += 1
            if self.num_restarts:
                top = np.argsort(-raw_values, kind="stable")[: self.num_restarts]
                starts.append(raw[top])
        U0 = np.unique(np.concatenate(starts), axis=0)
        solver = self._solver()
        opts = {
            **SOLVER_DEFAULTS[solver],
            **{k: v for k, v in self.options.items() if k in SOLVER_DEFAULTS[solver]},
        }
        if solver == "newton":
            U, values, info = maximize_in_unit_box(
                lambda U_, order: self._acq_unit(U_, order, lo, width), U0, **opts
            )
        else:
            U, values, info = _maximize_lbfgsb(
                lambda U_, order: self._acq_unit(U_, order, lo, width), U0, opts
            )
        cand, cand_values = np.concatenate([U, raw]), np.concatenate([values, raw_values])
        i = int(np.argmax(cand_values))
        x = box[0] + torch.from_numpy(cand[i].copy()) * (box[1] - box[0])
        x = torch.minimum(torch.maximum(x, box[0]), box[1])  # final guard against round-off
        self.proposals.append(x.clone())
        self.last_info = {
            "acq_value": float(cand_values[i]),
            "center": center.clone(),
            "trust_lower": box[0].clone(),
            "trust_upper": box[1].clone(),
            "fit_time_s": self._tell_time,
            "acq_time_s": time.perf_counter() - t0,
            "n_train": self.n_told,
            "n_starts": U0.shape[0],
            "n_evals": n_evals + info["evaluations"],
            "iterations": info["iterations"],
            "solver": solver,
        }
        return x
