r"""From a differentiable model of the objective to a :class:`PhysicsPrior`."""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Sequence
from typing import Any

import torch
from torch import Tensor

from pigp_torch._multistart import find_optimum
from pigp_torch._utils import as_knob_tensor, check_bounds
from pigp_torch.prior.hessian import log_excess_hessian, repair_negative_definite
from pigp_torch.prior.physics_prior import PhysicsPrior

#: Newton-step size (in correlation lengths) above which x0 is reported as not stationary.
GRADIENT_WARN_TOL = 1e-3


def prior_from_model(
    f: Callable[[Tensor], Tensor],
    bounds,
    *,
    f_inf: float,
    noise: float,
    x0=None,
    n_starts: int = 16,
    seed: int = 0,
    amplitude: float | None = None,
    knob_names: Sequence[str] | None = None,
    provenance: dict[str, Any] | None = None,
    rel_floor: float = 1e-6,
) -> PhysicsPrior:
    r"""Compute the physics prior of a PI-GP from a differentiable model ``f`` of the objective.

    1. :math:`\mathbf x_0`: the maximum of ``f`` in ``bounds`` (:func:`find_optimum`) unless given.
    2. :math:`G, H`: gradient and Hessian of :math:`\log(f - f_\infty)` at :math:`\mathbf x_0`
       by autograd (:func:`log_excess_hessian`).
    3. :math:`H` is made negative definite (:func:`repair_negative_definite`, warns if changed).
    4. Precision :math:`\Sigma = -H/2`; amplitude
       :math:`\sigma_f^2 = (f(\mathbf x_0) - f_\infty)^2 / 12` (variance of a uniform
       distribution spanning the objective's range) unless given.

    If :math:`\mathbf x_0` is not stationary (it lies on a bound, the search did not converge, or
    a non-optimal ``x0`` was given), i.e. the Newton step
    :math:`\sqrt{G^\top (-H)^{-1} G}` exceeds :data:`GRADIENT_WARN_TOL` correlation lengths, a
    warning is issued. :math:`G` is kept in ``prior.gradient``: the Gaussian basis function then
    has a linear term :math:`G^\top (\mathbf x - \mathbf x_0)` in its exponent, but a stationary
    kernel uses only the curvature, so the GP ignores it.

    Args:
        f: differentiable callable mapping ``N x d`` float64 knob settings to ``N`` objective
            values (to be MAXIMIZED).
        bounds: ``2 x d`` knob limits.
        f_inf: background level :math:`f_\infty` of ``f`` (prior mean of the GP).
        noise: measurement noise standard deviation :math:`\sigma_n`.
        x0: optional ``d`` expansion point; skips the optimum search.
        n_starts: Sobol starts of the optimum search.
        seed: seed of the optimum search.
        amplitude: kernel variance :math:`\sigma_f^2`; default
            :math:`(f(\mathbf x_0) - f_\infty)^2 / 12`.
        knob_names: ``d`` names; default ``["x0", "x1", ...]``.
        provenance: extra JSON-able information stored with the prior; the build details are
            added under the key ``"build"``.
        rel_floor: relative eigenvalue floor of the negative-definite repair.

    Returns:
        The :class:`PhysicsPrior`.

    Raises:
        ValueError: ``f_inf >= f(x0)``, a non-finite Hessian, ``knob_names`` of the wrong length,
            bad ``bounds``/``x0``, or any invalid prior field.
    """
    b = check_bounds(bounds)
    d = b.shape[1]
    if knob_names is None:
        knob_names = [f"x{i}" for i in range(d)]
    knob_names = list(knob_names)
    if len(knob_names) != d:
        raise ValueError(f"knob_names has {len(knob_names)} entries but bounds have {d} knobs")

    if x0 is None:
        x0, _ = find_optimum(f, b, n_starts=n_starts, seed=seed)
        x0_source = "find_optimum"
    else:
        x0_t = x0 if isinstance(x0, Tensor) else torch.as_tensor(x0, dtype=torch.float64)
        if x0_t.dim() != 1:
            raise ValueError(f"x0 must have shape ({d},), got {tuple(x0_t.shape)}")
        x0 = as_knob_tensor(x0_t, d, name="x0")[0][0]
        x0_source = "given"

    H, G, f_x0 = log_excess_hessian(f, x0, f_inf)
    H_rep, repair_info = repair_negative_definite(H, rel_floor=rel_floor)
    newton = torch.linalg.solve(-H_rep, G)
    newton_step = math.sqrt(max((G @ newton).item(), 0.0))
    if newton_step > GRADIENT_WARN_TOL:
        warnings.warn(
            f"x0 is not a stationary point of log(f - f_inf): the Newton step to the maximum is "
            f"{newton_step:.3g} correlation lengths (|G| = {G.norm().item():.3g}); x0 may lie on "
            "a bound or the search did not converge. The gradient is kept in prior.gradient; "
            "the kernel uses only the curvature.",
            RuntimeWarning,
            stacklevel=2,
        )
    if amplitude is None:
        amplitude = (f_x0 - float(f_inf)) ** 2 / 12.0

    build = {
        "x0_source": x0_source,
        "n_starts": n_starts if x0_source == "find_optimum" else None,
        "seed": seed if x0_source == "find_optimum" else None,
        "hessian_eigenvalues": repair_info["eigenvalues_before"],
        "repair_n_clipped": repair_info["n_clipped"],
        "repair_relative_change": repair_info["relative_change"],
        "rel_floor": rel_floor,
        "newton_step": newton_step,
    }
    prov = dict(provenance or {})
    prov["build"] = build
    return PhysicsPrior(
        x0=x0,
        f_x0=f_x0,
        f_inf=f_inf,
        precision=-0.5 * H_rep,
        amplitude=amplitude,
        noise=noise,
        knob_names=knob_names,
        bounds=b,
        gradient=G,
        provenance=prov,
    )
