r"""The search for the model's peak :math:`x_0` when none is given: sampled starts, then a
multi-start climb (:func:`search_peak`)."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor

from pigp_torch._utils import DTYPE, as_knob_tensor
from pigp_torch._utils.multistart import maximize_from

#: Rows of f evaluated at once while sampling.
SAMPLE_CHUNK = 1024


def _evaluate_chunked(f: Callable[[Tensor], Tensor], X: Tensor) -> Tensor:
    """``f`` on the ``N x d`` rows of ``X``, no gradients: ``N`` values, ``-inf`` if not finite."""
    out = []
    with torch.no_grad():
        for Xc in X.split(SAMPLE_CHUNK):
            y = torch.as_tensor(f(Xc)).detach().to(DTYPE).reshape(-1)
            if y.numel() != Xc.shape[0]:
                raise ValueError(
                    f"f must map an N x d tensor to N values; got {y.numel()} values for "
                    f"input {tuple(Xc.shape)}"
                )
            out.append(y)
    y = torch.cat(out) if out else torch.empty(0, dtype=DTYPE)
    return torch.where(torch.isfinite(y), y, torch.full_like(y, -torch.inf))


def search_peak(
    f: Callable[[Tensor], Tensor],
    b: Tensor,
    f_inf: float,
    n_starts: int,
    seed: int,
    n_samples: int,
    n_sample_starts: int,
    x_init,
) -> dict[str, Any]:
    r"""Search the maximizer :math:`\mathbf x_0` of ``f`` in the box ``b`` (``2 x d``).

    ``f`` is evaluated (without gradients, in chunks of :data:`SAMPLE_CHUNK` rows) on the first
    ``n_starts + n_samples`` points of a scrambled Sobol sequence of the box seeded with
    ``seed``, and on the rows of ``x_init`` (``d`` or ``k x d``, clipped into the box). Batched
    L-BFGS-B (:func:`~pigp_torch._utils.multistart.maximize_from`, in unit-cube coordinates)
    then starts from the first ``n_starts`` Sobol points, the ``n_sample_starts`` best of the
    other ``n_samples`` points and every row of ``x_init``. A start with
    :math:`e = f - f_\infty > 0` climbs :math:`g = \log e` (same maximizer as :math:`f`, but its
    gradient stays useful far in the tails of a peak, where that of :math:`f` underflows; the
    search does not leave :math:`e > 0`); a start with :math:`e \le 0` climbs :math:`f`. The
    end point with the largest :math:`f` is polished by a search of its own (the joint problem
    stops when its slowest start does); :math:`\mathbf x_0` is the better of the two. Cost:
    ``n_starts + n_samples`` (plus the rows of ``x_init``) evaluations of ``f`` without
    gradients, then those of the L-BFGS-B iterations (each one batched call for all starts).

    Returns:
        ``{"x0", "f_x0", "best_sample_excess", "range", "n_evaluated", "n_local_starts"}``:
        the ``d`` maximizer, :math:`f` there, the best sampled :math:`e`, the range of
        :math:`f` over the samples and :math:`\mathbf x_0` (zero for a flat ``f``), and the
        counts of sampled points and local starts.

    Raises:
        ValueError: a negative count, no start at all, or ``f`` non-finite everywhere.
    """
    for name, val in (
        ("n_starts", n_starts),
        ("n_samples", n_samples),
        ("n_sample_starts", n_sample_starts),
    ):
        if val < 0:
            raise ValueError(f"{name} must be >= 0, got {val}")
    lo, width = b[0], b[1] - b[0]
    Z_sobol, Z_init, y_all = _sample(f, b, n_starts + n_samples, seed, x_init)
    n_sobol = Z_sobol.shape[0]
    y_pool = y_all[n_starts:n_sobol]
    best = y_pool.argsort(descending=True)[: min(n_sample_starts, y_pool.numel())]
    best = best[torch.isfinite(y_pool[best])]
    Z0 = torch.cat([Z_sobol[:n_starts], Z_sobol[n_starts + best], Z_init])
    y0 = torch.cat([y_all[:n_starts], y_pool[best], y_all[n_sobol:]])
    if Z0.shape[0] == 0:
        raise ValueError("no starting point: give n_starts > 0, n_sample_starts > 0 or x_init")
    X_end = _climb(f, b, f_inf, Z0, y0)
    y_end = _evaluate_chunked(f, X_end)
    if not torch.isfinite(y_end).any():
        raise ValueError("f was not finite at any end point of the local search")
    i = int(y_end.argmax())
    # polish the best end point alone: the joint problem stops when its slowest start does
    x_pol = _climb(f, b, f_inf, ((X_end[i] - lo) / width).clamp(0.0, 1.0)[None], y_end[i, None])
    y_pol = _evaluate_chunked(f, x_pol)
    if y_pol[0] >= y_end[i]:
        X_end, y_end, i = torch.cat([X_end, x_pol]), torch.cat([y_end, y_pol]), X_end.shape[0]
    finite = y_all[torch.isfinite(y_all)]
    return {
        "x0": X_end[i],
        "f_x0": float(y_end[i]),
        "best_sample_excess": float(finite.max()) - f_inf,
        # range of f over the samples and x0: zero for a flat f
        "range": max(float(finite.max()), float(y_end[i]))
        - min(float(finite.min()), float(y_end[i])),
        "n_evaluated": int(y_all.shape[0]),
        "n_local_starts": int(Z0.shape[0]),
    }


def _sample(f, b: Tensor, n_sobol: int, seed: int, x_init):
    """``f`` at the first ``n_sobol`` points of the scrambled Sobol sequence of seed ``seed``
    and at the rows of ``x_init`` (clipped into the box ``b``): ``(Z_sobol, Z_init, y)``, the
    points in unit-cube coordinates and the values at all of them, in that order."""
    d = b.shape[1]
    lo, width = b[0], b[1] - b[0]
    Z_sobol = (
        torch.quasirandom.SobolEngine(d, scramble=True, seed=seed).draw(n_sobol, dtype=DTYPE)
        if n_sobol
        else torch.empty(0, d, dtype=DTYPE)
    )
    Z_init = torch.empty(0, d, dtype=DTYPE)
    if x_init is not None:
        xi = as_knob_tensor(x_init, d, name="x_init")[0]
        Z_init = ((xi - lo) / width).clamp(0.0, 1.0)
    Z_all = torch.cat([Z_sobol, Z_init])
    if Z_all.shape[0] == 0:
        raise ValueError("no starting point: give n_starts > 0, n_samples > 0 or x_init")
    y_all = _evaluate_chunked(f, lo + width * Z_all)
    if not torch.isfinite(y_all).any():
        raise ValueError(f"f was not finite at any of the {Z_all.shape[0]} sampled points")
    return Z_sobol, Z_init, y_all


def _climb(
    f: Callable[[Tensor], Tensor], b: Tensor, f_inf: float, Z0: Tensor, y0: Tensor
) -> Tensor:
    """Batched L-BFGS-B from the unit-cube starts ``Z0`` (values ``y0`` of ``f``): a start with
    ``f > f_inf`` climbs log(f - f_inf) and stays where ``f > f_inf``, the others climb ``f``.
    Returns the ``k x d`` end points (knob units)."""
    use_log = y0 > f_inf  # per start, fixed: each start follows its own path

    def objective(X: Tensor) -> Tensor:
        y = torch.as_tensor(f(X)).to(DTYPE).reshape(-1)
        if y.numel() != X.shape[0]:
            raise ValueError(f"f must return one value per row, got shape {tuple(y.shape)}")
        y = y + 0.0 * X.sum(-1)  # keeps a graph if f ignores X
        e = y - f_inf
        pos = e > 0
        log_e = torch.log(torch.where(pos, e, torch.ones_like(e)))
        nan = torch.full_like(e, math.nan)  # a log start at e <= 0: penalized, the search backs off
        return torch.where(use_log, torch.where(pos, log_e, nan), y)

    return maximize_from(objective, b, Z0)[0]
