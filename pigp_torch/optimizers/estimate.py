r"""The setting the evidence supports: the best posterior mean among the visited settings.

With noisy readings the best reading is the luckiest one, not the best setting: of :math:`n`
readings of equal settings the smallest is about :math:`\sigma \sqrt{2 \ln n}` below their mean.
:func:`posterior_best` smooths the noise out with a Gaussian process on the scalar readings near
the best one and returns the visited setting whose posterior mean is best; an optimizer's
``recommend()`` leaves the knobs there at the end of a run.

The GP (knobs scaled to :math:`[0, 1]` by ``bounds``; readings standardized to mean 0, sd 1): the
``k`` readings nearest the best reading (default 30), a constant mean, a Matérn-5/2 kernel with
one length scale :math:`\ell` and the noise as a fraction :math:`\lambda` of the signal variance,

.. math:: K = \sigma_f^2 \big(R_\ell + \lambda I\big), \qquad
    \hat\sigma_f^2 = \tfrac1k\, y^\top (R_\ell + \lambda I)^{-1} y,

:math:`(\ell, \lambda)` by the largest marginal likelihood (with :math:`\sigma_f^2` profiled
out: :math:`-\tfrac k2 \ln \hat\sigma_f^2 - \tfrac12 \ln |R_\ell + \lambda I|`) over a grid:
:math:`\ell` = 0.25, 0.5, 1, 2, 4 times the median distance between the readings,
:math:`\lambda \in \{10^{-4}, 10^{-3}, 10^{-2}, 0.03, 0.1, 0.3, 1\}`. The posterior mean at the
readings is :math:`\mu = R_\ell (R_\ell + \lambda I)^{-1} y`; its best entry is returned. With
the smallest :math:`\lambda` the mean nearly interpolates and the best reading wins, so a smooth
noise-free objective keeps its best reading; noisy readings pick a large :math:`\lambda` and the
mean averages neighbours. The kernel is GPyTorch's Matérn-5/2; the fit is this grid, not
ML-II by gradient: on at most ``k`` points 35 Cholesky factorizations are cheap and the choice
is deterministic (the same setting for the same readings on every run).
"""

from __future__ import annotations

import math

import gpytorch
import torch

from pigp_torch._utils import DTYPE

__all__ = ["posterior_best", "posterior_fit"]

#: The grid of the fit (module docstring): length scales in units of the median distance
#: between the readings, noise-to-signal variance ratios.
LENGTH_FACTORS = (0.25, 0.5, 1.0, 2.0, 4.0)
NOISE_RATIOS = (1e-4, 1e-3, 1e-2, 0.03, 0.1, 0.3, 1.0)


def posterior_best(X, Y, bounds, *, maximize: bool = False, k: int = 30) -> int:
    r"""The index of the visited setting with the best GP posterior mean (module docstring).

    Args:
        X: ``n x d`` visited settings (knob units); Y: ``n`` readings.
        bounds: ``2 x d`` knob bounds (the scale of each knob).
        maximize: ``True``: the largest mean is best (default ``False``: the smallest).
        k: readings nearest the best reading in the fit (default 30; all when fewer).

    Returns:
        An index into ``X`` (the best reading's when fewer than 3 readings are told).
    """
    return posterior_fit(X, Y, bounds, maximize=maximize, k=k)[0]


def posterior_fit(X, Y, bounds, *, maximize: bool = False, k: int = 30) -> tuple[int, float]:
    r""":func:`posterior_best`'s index and the noise sd of its fit (the units of ``Y``):
    :math:`\hat\sigma_n = s_y \sqrt{\lambda\, \hat\sigma_f^2}` (:math:`s_y` the sd of the
    fitted readings, :math:`\lambda` and :math:`\hat\sigma_f^2` of the standardized fit; 0 when
    fewer than 3 readings or all equal)."""
    X = torch.as_tensor(X, dtype=DTYPE)
    y = torch.as_tensor(Y, dtype=DTYPE).reshape(-1)
    sign = -1.0 if maximize else 1.0
    best = int((sign * y).argmin())
    if y.numel() < 3:
        return best, 0.0
    b = torch.as_tensor(bounds, dtype=DTYPE)
    Z = (X - b[0]) / (b[1] - b[0])
    near = torch.argsort((Z - Z[best]).norm(dim=-1))[: max(3, int(k))]
    Z, v = Z[near], sign * y[near]
    sd = v.std()
    if not bool(sd > 0):
        return best, 0.0
    v = (v - v.mean()) / sd
    D = torch.cdist(Z, Z)
    scale = D[D > 0].median() if bool((D > 0).any()) else torch.tensor(1.0, dtype=DTYPE)
    eye = torch.eye(len(v), dtype=DTYPE)
    kernel = gpytorch.kernels.MaternKernel(nu=2.5).to(DTYPE)  # the correlation R_l
    fit = None
    for f in LENGTH_FACTORS:
        with torch.no_grad():
            kernel.lengthscale = f * scale
            R = kernel(Z).to_dense()
        for lam in NOISE_RATIOS:
            L = torch.linalg.cholesky(R + lam * eye)
            alpha = torch.cholesky_solve(v[:, None], L)[:, 0]
            ll = -0.5 * len(v) * math.log(float(v @ alpha) / len(v)) - float(
                L.diagonal().log().sum()
            )
            if fit is None or ll > fit[0]:
                fit = (ll, R, alpha, lam * float(v @ alpha) / len(v))
    mean = fit[1] @ fit[2]
    return int(near[int(mean.argmin())]), float(sd) * fit[3] ** 0.5
