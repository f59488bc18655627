r"""From a differentiable model of the objective to a :class:`PhysicsPrior`
(:func:`prior_from_model`).

For a Gaussian peak :math:`f = f_\infty + A \exp(-\tfrac12 \boldsymbol\delta^\top P
\boldsymbol\delta)`, :math:`\boldsymbol\delta = \mathbf x - \mathbf c`, :math:`g = \log(f -
f_\infty)` is the quadratic :math:`\log A - \tfrac12 \boldsymbol\delta^\top P \boldsymbol\delta`,
so :math:`\mathbf x_0 = \mathbf c`, :math:`H = -P` and :math:`\Sigma = P / 2` exactly.

*Check of a searched* :math:`\mathbf x_0`. A knob is *on a bound* when it lies within
:data:`ON_BOUND_TOL` of its range from a limit and :math:`G = \nabla \log(f - f_\infty)` points
out of the box there; the other knobs are *free* (index set :math:`F`). :math:`\mathbf x_0` is
rejected unless

- :math:`e(\mathbf x_0) = f(\mathbf x_0) - f_\infty > 0`, above :data:`BACKGROUND_REL_TOL`
  :math:`\cdot \max(|f_\infty|, |f(\mathbf x_0)|)` and at least :data:`MIN_EXCESS_FRACTION` of
  the best sampled excess;
- :math:`f` is not constant on the samples and :math:`\mathbf x_0`;
- :math:`H_{FF}` is not zero and its largest eigenvalue is at most
  :data:`POSITIVE_CURVATURE_TOL` times its largest :math:`|\lambda|` (a mild repair);
- the Newton step of the free knobs :math:`\sqrt{G_F^\top (-\tilde H_{FF})^{-1} G_F}`
  (:math:`\tilde H` repaired) is at most :data:`NEWTON_STEP_MAX` correlation lengths.

*Stationarity.* If :math:`\mathbf x_0` is not stationary in all knobs (it lies on a bound, the
search did not converge, or a non-optimal ``x0`` was given), i.e. the Newton step
:math:`\sqrt{G^\top (-\tilde H)^{-1} G}` exceeds :data:`GRADIENT_WARN_TOL` correlation lengths,
a warning is issued: a maximum on a bound is legitimate (the peak may lie beyond the box).
:math:`G` is kept in ``prior.gradient``: the Gaussian basis function then has a linear term
:math:`G^\top (\mathbf x - \mathbf x_0)` in its exponent, but a stationary kernel uses only the
curvature, so the GP ignores it.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Sequence
from typing import Any

import torch
from torch import Tensor

from pigp_torch._utils import DTYPE, as_knob_tensor, check_bounds
from pigp_torch.prior.hessian import log_excess_hessian, repair_negative_definite
from pigp_torch.prior.peak_search import search_peak
from pigp_torch.prior.physics_prior import PhysicsPrior

#: Newton-step size (in correlation lengths) above which x0 is reported as not stationary.
GRADIENT_WARN_TOL = 1e-3
#: Newton step (correlation lengths) in the free knobs above which a searched x0 is rejected.
NEWTON_STEP_MAX = 0.1
#: A searched x0 must reach this fraction of the best sampled excess f - f_inf.
MIN_EXCESS_FRACTION = 0.5
#: Excess f(x0) - f_inf at or below this fraction of max(|f_inf|, |f(x0)|) is the background.
BACKGROUND_REL_TOL = 1e-8
#: Largest eigenvalue of the free knobs' Hessian, relative to the largest |eigenvalue|,
#: tolerated at a searched x0 (the repair clips it; above this x0 is a saddle, not a maximum).
POSITIVE_CURVATURE_TOL = 1e-2
#: A knob within this fraction of its range from a limit is on the bound.
ON_BOUND_TOL = 1e-9


def prior_from_model(
    f: Callable[[Tensor], Tensor],
    bounds,
    *,
    f_inf: float,
    noise: float,
    x0=None,
    n_starts: int = 16,
    seed: int = 0,
    n_samples: int = 4096,
    n_sample_starts: int = 8,
    x_init=None,
    amplitude: float | None = None,
    knob_names: Sequence[str] | None = None,
    provenance: dict[str, Any] | None = None,
    rel_floor: float = 1e-6,
) -> PhysicsPrior:
    r"""Compute the physics prior of a PI-GP from a differentiable model ``f`` of the objective.

    With the excess :math:`e(\mathbf x) = f(\mathbf x) - f_\infty` over the background and
    :math:`g = \log e`:

    1. :math:`\mathbf x_0 = \arg\max_{\mathbf l \le \mathbf x \le \mathbf u} f(\mathbf x)`,
       unless ``x0`` is given (the search: :func:`~pigp_torch.prior.peak_search.search_peak`;
       a searched :math:`\mathbf x_0` is checked as the module docstring says, a given one only
       for :math:`f(\mathbf x_0) > f_\infty` and a finite Hessian).
    2. :math:`G = \nabla g(\mathbf x_0)`, :math:`H = \nabla^2 g(\mathbf x_0)` by autograd
       (:func:`log_excess_hessian`).
    3. :math:`H` is made negative definite (:func:`repair_negative_definite`, warns if changed);
       a warning if :math:`\mathbf x_0` is not stationary (module docstring).
    4. Precision :math:`\Sigma = -H/2`; amplitude
       :math:`\sigma_f^2 = e(\mathbf x_0)^2 / 12` (variance of a uniform distribution spanning
       the objective's range) unless given (a Gaussian peak: :math:`\Sigma = P/2` exactly).

    Args:
        f: differentiable callable mapping ``N x d`` float64 knob settings to ``N`` objective
            values (to be MAXIMIZED).
        bounds: ``2 x d`` knob limits.
        f_inf: background level :math:`f_\infty` of ``f`` (prior mean of the GP).
        noise: measurement noise standard deviation :math:`\sigma_n`.
        x0: optional ``d`` expansion point; skips the search and its check.
        n_starts, seed, n_samples, n_sample_starts, x_init: the search's Sobol starts (>= 0,
            default 16), the seed of its Sobol sequence (0), the further sampled points (>= 0,
            4096), the number of best samples it also starts from (>= 0, 8), and optional
            ``d`` or ``k x d`` extra starts, e.g. the machine's present setting.
        amplitude: kernel variance :math:`\sigma_f^2`; default
            :math:`(f(\mathbf x_0) - f_\infty)^2 / 12`.
        knob_names: ``d`` names; default ``["x0", "x1", ...]``.
        provenance: extra JSON-able information stored with the prior; the build details are
            added under the key ``"build"``.
        rel_floor: relative eigenvalue floor of the negative-definite repair.

    Returns:
        The :class:`PhysicsPrior`.

    Raises:
        ValueError: the searched ``x0`` fails the check (the message gives what was found and
            what to do); ``f_inf >= f(x0)``; a non-finite Hessian; no start, or ``f``
            non-finite at every start; a negative count; ``knob_names`` of the wrong length;
            bad ``bounds``, ``x0`` or ``x_init``; or any invalid prior field.
    """
    b = check_bounds(bounds)
    knob_names = _knob_names(knob_names, b.shape[1])
    f_inf = float(f_inf)
    search = None
    if x0 is None:
        search = search_peak(f, b, f_inf, n_starts, seed, n_samples, n_sample_starts, x_init)
        _check_excess(search, f_inf, knob_names)
        x0 = search["x0"]
    else:
        x0 = _given_x0(x0, b.shape[1])
    H_rep, G, f_x0, build = _curvature_at(f, x0, f_inf, b, search, knob_names, rel_floor)
    amplitude = (f_x0 - f_inf) ** 2 / 12.0 if amplitude is None else amplitude
    searched = (n_starts, seed, n_samples, n_sample_starts) if search is not None else None
    build = {**_build_record(search, searched), **build}
    return PhysicsPrior(
        x0=x0, f_x0=f_x0, f_inf=f_inf, precision=-0.5 * H_rep, amplitude=amplitude,
        noise=noise, knob_names=knob_names, bounds=b, gradient=G,
        provenance={**(provenance or {}), "build": build},
    )  # fmt: skip


def _curvature_at(f, x0: Tensor, f_inf: float, b: Tensor, search, knob_names, rel_floor):
    r"""Steps 2 and 3 of :func:`prior_from_model` at ``x0``: :math:`G`, :math:`H` by autograd,
    the check of a searched ``x0`` (``search`` not ``None``), the negative-definite repair and
    the stationarity warning. Returns ``(H_repaired, G, f(x0), record)``, ``record`` the
    repair's and the Newton step's part of the ``"build"`` provenance."""
    H, G, f_x0 = log_excess_hessian(f, x0, f_inf)
    on_bound = _on_bound(x0, G, b)
    if search is not None:
        _check_curvature(search, H, G, on_bound, f_inf, knob_names, rel_floor)
    H_rep, repair_info = repair_negative_definite(H, rel_floor=rel_floor)
    newton_step = _newton_step(H_rep, G)
    _warn_if_not_stationary(newton_step, G, on_bound, knob_names)
    record = {
        "hessian_eigenvalues": repair_info["eigenvalues_before"],
        "repair_n_clipped": repair_info["n_clipped"],
        "repair_relative_change": repair_info["relative_change"],
        "rel_floor": rel_floor,
        "newton_step": newton_step,
        "knobs_on_bound": [knob_names[i] for i in on_bound.nonzero().flatten().tolist()],
    }
    return H_rep, G, f_x0, record


def _build_record(search, searched) -> dict:
    """Where x0 came from, for the ``"build"`` provenance: the search's settings ``searched =
    (n_starts, seed, n_samples, n_sample_starts)`` (``None``: x0 was given) and its best
    sampled excess."""
    n_starts, seed, n_samples, n_sample_starts = searched or (None,) * 4
    return {
        "x0_source": "given" if search is None else "search",
        "n_starts": n_starts,
        "seed": seed,
        "n_samples": n_samples,
        "n_sample_starts": n_sample_starts,
        "best_sample_excess": None if search is None else search["best_sample_excess"],
    }


def _knob_names(knob_names: Sequence[str] | None, d: int) -> list[str]:
    """``d`` knob names: the given ones (checked) or ``["x0", "x1", ...]``."""
    names = [f"x{i}" for i in range(d)] if knob_names is None else list(knob_names)
    if len(names) != d:
        raise ValueError(f"knob_names has {len(names)} entries but bounds have {d} knobs")
    return names


def _given_x0(x0, d: int) -> Tensor:
    """A given expansion point as a ``d`` float64 tensor (a ``d`` vector, nothing else)."""
    x0_t = x0 if isinstance(x0, Tensor) else torch.as_tensor(x0, dtype=DTYPE)
    if x0_t.dim() != 1:
        raise ValueError(f"x0 must have shape ({d},), got {tuple(x0_t.shape)}")
    return as_knob_tensor(x0_t, d, name="x0")[0][0]


def _warn_if_not_stationary(
    newton_step: float, G: Tensor, on_bound: Tensor, knob_names: list[str]
) -> None:
    """The RuntimeWarning for an x0 whose Newton step exceeds :data:`GRADIENT_WARN_TOL`."""
    if newton_step <= GRADIENT_WARN_TOL:
        return
    where = (
        f"knobs {[knob_names[i] for i in on_bound.nonzero().flatten().tolist()]} lie on a "
        "bound with f rising across it"
        if on_bound.any()
        else "x0 may lie on a bound or the search did not converge"
    )
    warnings.warn(
        f"x0 is not a stationary point of log(f - f_inf): the Newton step to the maximum is "
        f"{newton_step:.3g} correlation lengths (|G| = {G.norm().item():.3g}); {where}. "
        "The gradient is kept in prior.gradient; the kernel uses only the curvature.",
        RuntimeWarning,
        stacklevel=4,
    )


def _on_bound(x0: Tensor, G: Tensor, b: Tensor) -> Tensor:
    """``d`` bool: knob on a limit with the gradient of log(f - f_inf) pointing out of the box."""
    tol = ON_BOUND_TOL * (b[1] - b[0])
    return ((x0 >= b[1] - tol) & (G > 0)) | ((x0 <= b[0] + tol) & (G < 0))


def _newton_step(H_neg_def: Tensor, G: Tensor) -> float:
    r""":math:`\sqrt{G^\top (-H)^{-1} G}` (correlation lengths) for a negative-definite ``H``."""
    if G.numel() == 0:
        return 0.0
    step = torch.linalg.solve(-H_neg_def, G)
    return math.sqrt(max((G @ step).item(), 0.0))


def _not_a_maximum(
    problem: str, search: dict[str, Any], f_inf: float, knob_names: list[str], extra: str = ""
) -> ValueError:
    """The ValueError for a searched x0 that is not a maximum: what was found, what to do."""
    return ValueError(
        f"prior_from_model: the search did not find a maximum of f ({problem}). Found "
        f"f(x0) = {search['f_x0']:.6g}, i.e. f(x0) - f_inf = {search['f_x0'] - f_inf:.3g}, vs "
        f"the best of {search['n_evaluated']} sampled points f - f_inf = "
        f"{search['best_sample_excess']:.3g}, with f_inf = {f_inf:.6g} "
        f"({search['n_local_starts']} local starts){extra}. Check f_inf (f must rise above it "
        "near the peak), give more samples (n_samples, n_sample_starts, n_starts) or starts "
        "near the peak (x_init), or give x0."
    )


def _check_excess(search: dict[str, Any], f_inf: float, knob_names: list[str]) -> None:
    """Reject a searched x0 on the background, below the best sample, or a flat ``f``."""
    e0, e_best = search["f_x0"] - f_inf, search["best_sample_excess"]
    scale = max(abs(f_inf), abs(search["f_x0"]))
    if search["n_evaluated"] > 1 and search["range"] <= 1e-14 * scale:
        problem = (
            f"f takes the same value at all {search['n_evaluated']} sampled points and at x0: "
            "it is flat there (or its peak is too narrow for the samples)"
        )
    elif not e0 > 0:
        problem = "f(x0) <= f_inf: f does not rise above the background f_inf"
    elif e0 <= BACKGROUND_REL_TOL * scale:
        problem = "f(x0) - f_inf is negligible: x0 lies on the flat background"
    elif e0 < MIN_EXCESS_FRACTION * e_best:
        problem = (
            f"f(x0) - f_inf is below {MIN_EXCESS_FRACTION:g} of the best sampled excess: the "
            "local search did not climb"
        )
    else:
        return
    raise _not_a_maximum(problem, search, f_inf, knob_names)


def _check_curvature(
    search: dict[str, Any],
    H: Tensor,
    G: Tensor,
    on_bound: Tensor,
    f_inf: float,
    knob_names: list[str],
    rel_floor: float,
) -> None:
    """Reject a searched x0 whose free knobs are not at a maximum of log(f - f_inf)."""
    free = (~on_bound).nonzero().flatten()
    if free.numel() == 0:
        return  # a corner of the box with f rising across every bound
    H_ff = H[free][:, free]
    G_f = G[free]
    eig = torch.linalg.eigvalsh(H_ff)
    lam_abs = eig.abs().max().item()
    bound_names = [knob_names[i] for i in on_bound.nonzero().flatten().tolist()]
    if lam_abs == 0.0:
        step, problem = math.inf, "the Hessian of log(f - f_inf) in the free knobs is zero"
    else:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the repair of the full H below warns once
            H_rep, _ = repair_negative_definite(H_ff, rel_floor=rel_floor)
        step = _newton_step(H_rep, G_f)
        lam_max = eig.max().item()
        if lam_max > POSITIVE_CURVATURE_TOL * lam_abs:
            problem = (
                f"the Hessian of log(f - f_inf) in the free knobs has a positive eigenvalue "
                f"{lam_max:.3g} (largest |eigenvalue| {lam_abs:.3g}): a saddle or a minimum"
            )
        elif step > NEWTON_STEP_MAX:
            problem = (
                f"x0 is not stationary in the free knobs: Newton step {step:.3g} correlation "
                f"lengths > {NEWTON_STEP_MAX:g}"
            )
        else:
            return
    extra = (
        f"; Newton step in the {free.numel()} free knobs {step:.3g} correlation lengths, "
        f"knobs on a bound: {bound_names or 'none'}"
    )
    raise _not_a_maximum(problem, search, f_inf, knob_names, extra)
