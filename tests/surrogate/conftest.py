r"""Synthetic loss-rate landscape with the shape of the coupling physics, for surrogate tests.

Tests get the helpers through fixtures (``landscape3``, ``make_landscape``, ``hessian_errors``),
never by importing this conftest.

.. math::

    f(x) = f_\infty + \frac{A}{\sqrt{1 + (x - \mu)^\top Q (x - \mu)}}, \qquad
    \nabla^2 \log(f - f_\infty)\big|_{x=\mu} = -Q.
"""

from __future__ import annotations

from dataclasses import dataclass

import pytest
import torch

F_INF = 0.2
AMPLITUDE = 1.5


@dataclass
class SyntheticLandscape:
    """Heavy-tailed bowl f_inf + A / sqrt(1 + q) with a known Hessian of the log excess."""

    q: torch.Tensor  # d x d SPD
    mu: torch.Tensor  # d, optimum
    bounds: torch.Tensor  # 2 x d
    f_inf: float = F_INF
    amplitude: float = AMPLITUDE

    @property
    def dim(self) -> int:
        return self.mu.shape[0]

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        dx = x - self.mu
        quad = torch.einsum("...i,ij,...j->...", dx, self.q, dx)
        return self.f_inf + self.amplitude / torch.sqrt(1.0 + quad)

    def hessian_log_excess(self) -> torch.Tensor:
        """Exact Hessian of log(f - f_inf) at the optimum: -Q."""
        return -self.q

    def sample(self, n: int, *, seed: int = 0, sigma_frac=0.15) -> torch.Tensor:
        """Half uniform over the box, half Gaussian around the optimum (clipped to the box).

        ``sigma_frac``: Gaussian width in units of the box half width; a pair ``(lo, hi)`` draws
        one width per sample, log-uniform in that range (fills the radii down to the optimum).
        """
        g = torch.Generator().manual_seed(seed)
        lo, hi = self.bounds
        n_uni = n // 2
        x_uni = lo + (hi - lo) * torch.rand(n_uni, self.dim, generator=g, dtype=torch.float64)
        if isinstance(sigma_frac, (tuple, list)):
            a, b = torch.log(torch.tensor(sigma_frac, dtype=torch.float64))
            u = torch.rand(n - n_uni, 1, generator=g, dtype=torch.float64)
            sigma_frac = torch.exp(a + (b - a) * u)
        sigma = sigma_frac * (hi - lo) / 2
        x_gau = self.mu + sigma * torch.randn(n - n_uni, self.dim, generator=g, dtype=torch.float64)
        x_gau = torch.maximum(torch.minimum(x_gau, hi), lo)
        return torch.cat([x_uni, x_gau])


def _make_landscape(
    dim: int = 13,
    *,
    half_width: float = 0.015,
    cond: float = 500.0,
    n_dominant: int = 3,
    mean_quad: float = 24.0,
    seed: int = 0,
) -> SyntheticLandscape:
    r"""Random correlated SPD :math:`Q` with ``n_dominant`` stiff directions and condition ``cond``.

    Eigenvalues: the dominant ones 1, 0.6, 0.36, ... (relative), the rest log-spaced from 0.08
    down to ``1/cond``; eigenvectors a random rotation. :math:`Q` is scaled so that the mean of
    :math:`q` over the box is ``mean_quad`` (24 gives :math:`f \approx 0.5` at typical box points).
    The optimum :math:`\mu` is uniform within 40 % of the half width around the box center.
    """
    g = torch.Generator().manual_seed(seed)
    v, _ = torch.linalg.qr(torch.randn(dim, dim, generator=g, dtype=torch.float64))
    dom = 0.6 ** torch.arange(min(n_dominant, dim), dtype=torch.float64)
    n_rest = dim - len(dom)
    rest = torch.logspace(torch.log10(torch.tensor(0.08)), -torch.log10(torch.tensor(cond)), n_rest)
    lam = torch.cat([dom, rest.to(torch.float64)]) if n_rest else dom
    q = v @ torch.diag(lam) @ v.T
    q = 0.5 * (q + q.T)
    bounds = torch.tensor([[-half_width] * dim, [half_width] * dim], dtype=torch.float64)
    mu = 0.4 * half_width * (2 * torch.rand(dim, generator=g, dtype=torch.float64) - 1)
    # Mean of q over the uniform box: tr(Q) * w^2 / 3 + (c - mu)^T Q (c - mu), with c = 0.
    mean_q = torch.trace(q) * half_width**2 / 3 + mu @ q @ mu
    q = q * (mean_quad / mean_q)
    return SyntheticLandscape(q=q, mu=mu, bounds=bounds)


def _hessian_errors(h_model: torch.Tensor, h_true: torch.Tensor, k: int = 3) -> dict:
    """Relative Frobenius error and |cosine| of the top-k eigenvectors (by |eigenvalue|)."""
    rel = float(torch.linalg.norm(h_model - h_true) / torch.linalg.norm(h_true))
    ev_m, vec_m = torch.linalg.eigh(0.5 * (h_model + h_model.T))
    ev_t, vec_t = torch.linalg.eigh(h_true)
    # Most negative eigenvalues = stiffest directions of a maximum.
    cos = [float(torch.abs(vec_m[:, i] @ vec_t[:, i])) for i in range(k)]
    return {
        "rel_frob": rel,
        "cos": cos,
        "eig_model": ev_m[:k].tolist(),
        "eig_true": ev_t[:k].tolist(),
    }


@pytest.fixture(scope="session")
def landscape3() -> SyntheticLandscape:
    """Quick 3-D landscape (condition number 50, one dominant direction)."""
    return _make_landscape(3, cond=50.0, n_dominant=1, seed=1)


@pytest.fixture(scope="session", name="make_landscape")
def make_landscape_fixture():
    """The landscape factory :func:`_make_landscape`."""
    return _make_landscape


@pytest.fixture(scope="session", name="hessian_errors")
def hessian_errors_fixture():
    """The Hessian comparison :func:`_hessian_errors`."""
    return _hessian_errors
