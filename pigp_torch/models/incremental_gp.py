r"""Exact GP posterior of a fixed full-precision RBF kernel, grown one reading at a time.

:class:`IncrementalGP` keeps the Cholesky factor, the inverse Gram matrix and the weights
between readings (:math:`O(n^2)` per reading) and gives the posterior mean and variance with
closed-form gradients and Hessians; :class:`IncrementalPosterior` is the
:class:`~pigp_torch.models.posterior.Posterior` of the Bayesian-optimization core on it.

Why hand-written rather than BoTorch: a BoTorch ``SingleTaskGP`` cannot be grown by one row
(``condition_on_observations`` builds a new model and its caches each time, with the autograd
overhead of GPyTorch on every acquisition evaluation), and an online step has a budget of tens of
milliseconds. The contract tests check it against ``SingleTaskGP`` with the same kernel and noise.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import scipy.linalg
import torch
from gpytorch import settings as gpytorch_settings

from pigp_torch.kernels._base import precision_cholesky
from pigp_torch.models.posterior import PosteriorBase, Prediction

#: Smallest noise variance, as GPyTorch's ``FixedNoiseGaussianLikelihood`` rounds up in float64
#: (so the posterior equals BoTorch's also for tiny noise, and the Gram stays invertible).
MIN_NOISE_VARIANCE = float(gpytorch_settings.min_fixed_noise.value(torch.float64))
#: Smallest posterior variance used for the standard deviation (BoTorch's ``min_var``).
MIN_VARIANCE = 1e-12


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


class IncrementalPosterior(PosteriorBase):
    r"""The :class:`~pigp_torch.models.posterior.Posterior` of an :class:`IncrementalGP`.

    Readings are added at :meth:`observe` (:math:`O(n^2)`), :meth:`fit` does nothing. The
    standard deviation is :math:`\sigma = \sqrt{\max(\sigma^2, 10^{-12})}` with
    :math:`\nabla\sigma = \nabla\sigma^2 / 2\sigma` and :math:`\nabla^2\sigma =
    \nabla^2\sigma^2 / 2\sigma - \nabla\sigma\nabla\sigma^\top / \sigma` (both zero where
    the variance sits below the floor). Orders 0, 1 and 2 (2 needs a constant prior mean).

    Args:
        gp: the incremental GP (kept as :attr:`gp`).
    """

    def __init__(self, gp: IncrementalGP) -> None:
        self.gp = gp

    @property
    def max_order(self) -> int:
        return 2 if self.gp.mean_fn is None else 1

    def observe(self, x, y: float) -> None:
        """Condition on one more reading ``y`` at ``x`` (``d``)."""
        self.gp.add(x.numpy(), y)

    def fit(self, X, Y) -> None:
        """Nothing to do: every reading was added at :meth:`observe`."""

    def train_mean(self, X) -> np.ndarray:
        """Posterior mean at the told points (``n``)."""
        return self.gp.train_mean()

    def predict(self, X: np.ndarray, order: int = 0) -> Prediction:
        """Mean and standard deviation at ``X: N x d`` with derivatives up to ``order``."""
        out = self.gp.predict(X, order)
        mu, var = out[0], out[1]
        small = var < MIN_VARIANCE
        sigma = np.sqrt(np.where(small, MIN_VARIANCE, var))
        if order == 0:
            return Prediction(mu, sigma)
        inv2s = np.where(small, 0.0, 0.5 / sigma)
        dsig = inv2s[:, None] * out[3]
        if order == 1:
            return Prediction(mu, sigma, out[2], dsig)
        hsig = inv2s[:, None, None] * out[5] - np.einsum(
            "N,Ni,Nj->Nij", np.where(small, 0.0, 1.0 / sigma), dsig, dsig
        )
        return Prediction(mu, sigma, out[2], dsig, out[4], hsig)
