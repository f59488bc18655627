r"""Hessians of :math:`\log(f - f_\infty)`: autograd, finite differences, negative-def. repair."""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor

from pigp_torch._utils import DTYPE, as_knob_tensor

Objective = Callable[[Tensor], Tensor]


def _point(x0, name: str = "x0") -> Tensor:
    t = x0 if isinstance(x0, Tensor) else torch.as_tensor(x0, dtype=DTYPE)
    if t.dim() != 1:
        raise ValueError(f"{name} must be a 1-D tensor of knob values, got shape {tuple(t.shape)}")
    return as_knob_tensor(t, t.shape[0], name=name)[0][0]


def _evaluate(f: Objective, X: Tensor) -> Tensor:
    """Call ``f`` on ``N x d`` points and return an ``N`` float64 tensor (validated)."""
    y = torch.as_tensor(f(X))
    if y.numel() != X.shape[0] or (y.dim() > 1 and y.shape[0] != X.shape[0]):
        raise ValueError(
            f"f must map an N x d tensor to N values; got output shape {tuple(y.shape)} "
            f"for input {tuple(X.shape)}"
        )
    return y.reshape(X.shape[0]).to(DTYPE)


def log_excess_hessian(f: Objective, x0, f_inf: float) -> tuple[Tensor, Tensor, float]:
    r"""Autograd gradient and Hessian of :math:`g(\mathbf x) = \log(f(\mathbf x) - f_\infty)`.

    .. math::
        G = \nabla g(\mathbf x_0), \qquad H = \nabla^2 g(\mathbf x_0).

    Args:
        f: differentiable callable mapping ``N x d`` float64 knob settings to ``N`` objective
            values (e.g. a neural-network surrogate; cast float32 networks inside ``f``).
        x0: ``d`` expansion point (knob units).
        f_inf: background level :math:`f_\infty`; must be below :math:`f(\mathbf x_0)`.

    Returns:
        ``(H, G, f_x0)``: ``d x d`` symmetric Hessian (1 / knob²), ``d`` gradient (1 / knob) and
        the float :math:`f(\mathbf x_0)`.

    Raises:
        ValueError: bad ``x0``, ``f(x0) <= f_inf``, or a non-finite gradient/Hessian.
    """
    x0 = _point(x0)
    f_inf = float(f_inf)
    with torch.no_grad():
        f_x0 = _evaluate(f, x0.unsqueeze(0)).item()
    if not math.isfinite(f_x0):
        raise ValueError(f"f(x0) is not finite ({f_x0})")
    if not f_x0 > f_inf:
        raise ValueError(f"f_inf ({f_inf}) must be below f(x0) ({f_x0}); log(f - f_inf) undefined")

    def g(x: Tensor) -> Tensor:
        return torch.log(_evaluate(f, x.unsqueeze(0))[0] - f_inf)

    x = x0.clone().requires_grad_(True)
    (G,) = torch.autograd.grad(g(x), x, allow_unused=True)
    G = torch.zeros_like(x0) if G is None else G.detach()
    H = torch.autograd.functional.hessian(g, x0.clone()).detach()
    H = 0.5 * (H + H.T)
    if not (torch.isfinite(H).all() and torch.isfinite(G).all()):
        raise ValueError("the Hessian or gradient of log(f - f_inf) at x0 is not finite")
    return H, G, f_x0


def finite_difference_hessian(
    f: Objective, x0, f_inf: float | None = None, step: float | Tensor = 1e-4
) -> tuple[Tensor, Tensor, float]:
    r"""Central-difference gradient and Hessian for black-box (non-differentiable) simulators.

    With :math:`g = \log(f - f_\infty)` if ``f_inf`` is given, else :math:`g = f`, steps
    :math:`h_i` and unit vectors :math:`\mathbf e_i`:

    .. math::
        H_{ii} = \frac{g(\mathbf x_0 + h_i \mathbf e_i) - 2 g(\mathbf x_0)
            + g(\mathbf x_0 - h_i \mathbf e_i)}{h_i^2}, \qquad
        H_{ij} = \frac{g_{++} - g_{+-} - g_{-+} + g_{--}}{4 h_i h_j},

    :math:`g_{\pm\pm} = g(\mathbf x_0 \pm h_i \mathbf e_i \pm h_j \mathbf e_j)`, and
    :math:`G_i = (g(\mathbf x_0 + h_i \mathbf e_i) - g(\mathbf x_0 - h_i \mathbf e_i)) / 2h_i`.
    All :math:`1 + 2d^2` points are evaluated in ONE call of ``f``. The truncation error is
    :math:`O(h^2)`, the round-off error :math:`O(\epsilon / h^2)`: choose ``step`` about 1e-3 to
    1e-2 of the correlation length (larger for noisy simulators).

    Args:
        f: callable mapping ``N x d`` float64 knob settings to ``N`` values.
        x0: ``d`` expansion point.
        f_inf: background level, or ``None`` to differentiate ``f`` itself.
        step: positive scalar or ``d`` per-knob steps (knob units).

    Returns:
        ``(H, G, f_x0)`` as in :func:`log_excess_hessian`.

    Raises:
        ValueError: bad ``x0`` or ``step``, ``f <= f_inf`` at a stencil point, or non-finite
            values of ``f``.
    """
    x0 = _point(x0)
    d = x0.shape[0]
    h = (
        torch.as_tensor(step).to(DTYPE)
        if isinstance(step, Tensor)
        else torch.tensor(step, dtype=DTYPE)
    )
    if h.dim() == 0:
        h = h.expand(d).clone()
    if h.shape != (d,) or not (torch.isfinite(h).all() and (h > 0).all()):
        raise ValueError(f"step must be a positive scalar or {d} positive values, got {step!r}")

    eye = torch.diag(h)
    iu, ju = torch.triu_indices(d, d, offset=1)
    pts = [x0.unsqueeze(0), x0 + eye, x0 - eye]
    for si, sj in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
        pts.append(x0 + si * eye[iu] + sj * eye[ju])
    X = torch.cat(pts)
    with torch.no_grad():
        y = _evaluate(f, X)
    if not torch.isfinite(y).all():
        raise ValueError("f returned NaN or inf on the finite-difference stencil")
    f_x0 = y[0].item()
    if f_inf is not None:
        f_inf = float(f_inf)
        if not (y > f_inf).all():
            raise ValueError(
                f"f_inf ({f_inf}) must be below f on the whole stencil (min {y.min().item()})"
            )
        y = torch.log(y - f_inf)

    n_pairs = iu.numel()
    g0, gp, gm = y[0], y[1 : d + 1], y[d + 1 : 2 * d + 1]
    gpp, gpm, gmp, gmm = y[2 * d + 1 :].split(n_pairs)
    H = torch.diag((gp - 2 * g0 + gm) / h**2)
    off = (gpp - gpm - gmp + gmm) / (4 * h[iu] * h[ju])
    H[iu, ju] = off
    H[ju, iu] = off
    G = (gp - gm) / (2 * h)
    return H, G, f_x0


def repair_negative_definite(H: Tensor, rel_floor: float = 1e-6) -> tuple[Tensor, dict[str, Any]]:
    r"""Make a Hessian negative definite by clipping its eigenvalues.

    With :math:`H = V \Lambda V^\top` and floor
    :math:`\epsilon = \text{rel\_floor} \cdot \max_i |\lambda_i|`:

    .. math:: \tilde H = V \min(\Lambda, -\epsilon) V^\top .

    Positive (or too small) curvature — a saddle, a ridge, noise in a finite-difference Hessian —
    becomes a weak negative curvature, i.e. a long correlation length in that direction. If
    anything changes, a warning reports the number of clipped eigenvalues and the relative
    Frobenius change :math:`\lVert \tilde H - H \rVert_F / \lVert H \rVert_F`.

    Args:
        H: ``d x d`` symmetric matrix.
        rel_floor: relative floor :math:`\epsilon / \max|\lambda|`, in (0, 1).

    Returns:
        ``(H_repaired, info)``: the ``d x d`` negative-definite matrix (``H`` itself, symmetrized,
        when no eigenvalue is clipped) and a JSON-able dict with ``n_clipped``,
        ``relative_change``, ``floor``, ``eigenvalues_before`` and ``eigenvalues_after``.

    Raises:
        ValueError: not square, non-finite, not symmetric, all-zero, or a bad ``rel_floor``.
    """
    H = H if isinstance(H, Tensor) else torch.as_tensor(H, dtype=DTYPE)
    if H.dim() != 2 or H.shape[0] != H.shape[1] or H.shape[0] == 0:
        raise ValueError(f"H must be a non-empty square matrix, got shape {tuple(H.shape)}")
    H = H.detach().to(DTYPE)
    if not torch.isfinite(H).all():
        raise ValueError("H contains NaN or inf")
    if not 0 < rel_floor < 1:
        raise ValueError(f"rel_floor must lie in (0, 1), got {rel_floor}")
    scale = H.abs().max().item()
    if scale == 0:
        raise ValueError(
            "H is zero: the objective has no curvature at x0 (or is not differentiable)"
        )
    if (H - H.T).abs().max().item() > 1e-8 * scale:
        raise ValueError("H must be symmetric")
    H = 0.5 * (H + H.T)
    eig, V = torch.linalg.eigh(H)
    floor = rel_floor * eig.abs().max().item()
    clipped = eig > -floor
    n_clipped = int(clipped.sum().item())
    eig_new = eig.clamp(max=-floor)
    if n_clipped:
        H_new = V @ torch.diag(eig_new) @ V.T
        H_new = 0.5 * (H_new + H_new.T)
        rel_change = (torch.linalg.matrix_norm(H_new - H) / torch.linalg.matrix_norm(H)).item()
        warnings.warn(
            f"Hessian was not negative definite: clipped {n_clipped} of {H.shape[0]} eigenvalues "
            f"to <= -{floor:.3g} (relative Frobenius change {rel_change:.3g})",
            RuntimeWarning,
            stacklevel=2,
        )
    else:
        H_new, rel_change = H, 0.0
    info = {
        "n_clipped": n_clipped,
        "relative_change": rel_change,
        "floor": floor,
        "eigenvalues_before": eig.tolist(),
        "eigenvalues_after": eig_new.tolist(),
    }
    return H_new, info
