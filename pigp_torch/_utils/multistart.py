r"""Multi-start maximization of a differentiable, batched objective inside a box.

Used for the optimum of a simulated machine and of a surrogate (the prior's x0). All starts run
as ONE L-BFGS-B problem on the sum of their values: the sum is separable, so each start follows
its own path, and every step is a single batched evaluation of ``f`` (one call for all starts
instead of one per start).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch
from torch import Tensor

from pigp_torch._utils import DTYPE, as_knob_tensor, check_bounds
from pigp_torch._utils.lbfgsb import minimize_lbfgsb


def find_optimum(
    f: Callable[[Tensor], Tensor],
    bounds,
    n_starts: int = 16,
    seed: int = 0,
    x_init=None,
    maxiter: int = 2000,
    with_grad: bool = False,
) -> tuple[Tensor, float]:
    r"""Maximize ``f`` within ``bounds`` by multi-start L-BFGS-B with autograd gradients.

    .. math:: \mathbf x_0 = \arg\max_{\mathbf l \le \mathbf x \le \mathbf u} f(\mathbf x)

    The search runs in unit-cube coordinates :math:`\mathbf x = \mathbf l + (\mathbf u -
    \mathbf l) \odot \mathbf z` (knob ranges such as ±30 A would otherwise make the problem
    badly scaled). Starts: ``n_starts`` points of a scrambled Sobol sequence seeded with ``seed``,
    plus every row of ``x_init``. Deterministic for a given ``seed``. Non-finite values of ``f``
    (e.g. a setting without a stable beam) are penalized so the search leaves them.

    Args:
        f: differentiable callable mapping ``N x d`` float64 knob settings to ``N`` values.
        bounds: ``2 x d`` lower / upper limits.
        n_starts: number of Sobol starting points (>= 0; at least one start in total).
        seed: seed of the Sobol scrambling.
        x_init: optional ``d`` or ``k x d`` extra starting points (clipped into the box).
        maxiter: L-BFGS-B iteration limit.
        with_grad: ``f`` returns ``(values, gradients)``, ``N`` and ``N x d`` (a closed-form
            gradient, faster than building an autograd graph at every step); default: ``f``
            returns the values and autograd differentiates them.

    Returns:
        ``(x0, f_x0)``: ``d`` best setting found and its value (float).

    Raises:
        ValueError: bad bounds, ``x_init`` of the wrong size, no starting point, or ``f``
            non-finite at every start.
    """
    b = check_bounds(bounds)
    d = b.shape[1]
    lo, width = b[0], b[1] - b[0]
    if n_starts < 0:
        raise ValueError(f"n_starts must be >= 0, got {n_starts}")
    starts = []
    if n_starts:
        sobol = torch.quasirandom.SobolEngine(d, scramble=True, seed=seed)
        starts.append(sobol.draw(n_starts, dtype=DTYPE))
    if x_init is not None:
        xi = as_knob_tensor(x_init, d, name="x_init")[0]
        starts.append(((xi - lo) / width).clamp(0.0, 1.0))
    if not starts:
        raise ValueError("no starting point: give n_starts > 0 or x_init")
    X, y = maximize_from(f, b, torch.cat(starts), maxiter=maxiter, with_grad=with_grad)
    if not torch.isfinite(y).any():
        raise ValueError("f was not finite at any starting point")
    i = int(y.argmax())
    return X[i], float(y[i])


def maximize_from(
    f: Callable[[Tensor], Tensor],
    bounds,
    Z0: Tensor,
    maxiter: int = 2000,
    with_grad: bool = False,
) -> tuple[Tensor, Tensor]:
    r"""Run the batched L-BFGS-B of :func:`find_optimum` from given starts; return every end point.

    Each row of ``Z0`` is one start in unit-cube coordinates :math:`\mathbf z \in [0, 1]^d`
    (:math:`\mathbf x = \mathbf l + (\mathbf u - \mathbf l) \odot \mathbf z`). ``f`` is always
    called with all ``k`` rows in the order of ``Z0``, so it may treat row ``i`` as start ``i``
    (e.g. maximize a different monotone transform of the objective per start).

    Args:
        f: differentiable callable mapping ``k x d`` float64 knob settings to ``k`` values.
        bounds: ``2 x d`` lower / upper limits.
        Z0: ``k x d`` starts in the unit cube (``k >= 1``).
        maxiter: L-BFGS-B iteration limit.
        with_grad: ``f`` returns ``(values, gradients in knob units)`` (see
            :func:`find_optimum`).

    Returns:
        ``(X, y)``: ``k x d`` end points (knob units) and their ``k`` values of ``f``
        (``-inf`` where not finite).

    Raises:
        ValueError: bad bounds or ``Z0``, or ``f`` not returning one value per row.
    """
    b = check_bounds(bounds)
    d = b.shape[1]
    lo, width = b[0], b[1] - b[0]
    if Z0.dim() != 2 or Z0.shape[1] != d or Z0.shape[0] == 0:
        raise ValueError(f"Z0 must have shape (k, {d}) with k >= 1, got {tuple(Z0.shape)}")
    Z0 = Z0.detach().to(DTYPE).contiguous()
    k = Z0.shape[0]

    def evaluate(z: Tensor) -> Tensor:
        y = f(lo + width * z)
        y = (y[0] if with_grad else y).reshape(-1)
        if y.numel() != z.shape[0]:
            raise ValueError(f"f must return one value per row, got shape {tuple(y.shape)}")
        return y

    def neg_total(zflat: np.ndarray) -> tuple[float, np.ndarray]:
        z = torch.from_numpy(zflat.reshape(k, d)).to(DTYPE)
        if with_grad:
            with torch.no_grad():
                y, gx = f(lo + width * z)
            y = y.reshape(-1)
            ok = torch.isfinite(y)
            g = torch.where(ok.unsqueeze(-1), gx * width, torch.zeros_like(gx))
        else:
            z.requires_grad_(True)
            y = evaluate(z)
            ok = torch.isfinite(y)
        total = torch.where(ok, y, torch.zeros_like(y)).sum()
        if not with_grad:
            (g,) = torch.autograd.grad(total, z)
        penalty = 1e6 * float((~ok).sum())
        return -float(total.detach()) + penalty, -g.detach().numpy().reshape(-1)

    res = minimize_lbfgsb(
        neg_total,
        Z0.numpy().reshape(-1),
        bounds=[(0.0, 1.0)] * (k * d),
        maxiter=maxiter,
        maxfun=2 * maxiter,
        ftol=1e-15,
        gtol=1e-11,
    )
    Z = torch.from_numpy(res.x.reshape(k, d)).to(DTYPE)
    with torch.no_grad():
        y = evaluate(Z)
    y = torch.where(torch.isfinite(y), y, torch.full_like(y, -torch.inf))
    return lo + width * Z, y
