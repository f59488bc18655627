r"""Robust Conjugate Direction Search (RCDS) as an ask/tell optimizer.

RCDS (X. Huang et al., Nucl. Instrum. Methods A 726 (2013) 77) is Powell's conjugate-direction
method with a line optimizer made robust to measurement noise, designed for online tuning of
storage rings. Why our own implementation: :func:`scipy.optimize.minimize` (``method="Powell"``)
calls the objective through a callback and cannot pause for a machine, and its line search is not
noise aware; Xopt's RCDS generator would pull in Xopt and its pydantic/VOCS stack for one
algorithm. The algorithm below is a plain generator coroutine
(:mod:`pigp_torch.optimizers._coroutine`) that yields each point it wants measured.

Everything runs in the unit cube :math:`u = (x - x_{lo}) / (x_{hi} - x_{lo})` and minimizes
:math:`f` (:math:`f = -y` when maximizing). One cycle:

1. For each direction :math:`v_i` of the direction set, a line minimization from the current point
   :math:`u_m` (:func:`line_minimize`):

   * bracket: step :math:`t` forward with growing steps (:math:`t \to (1 + \varphi) t` while
     :math:`t < 0.1`, then :math:`t \to t + 0.1`; :math:`\varphi` the golden ratio) until a value
     lies significantly above the minimum found, :math:`f > f_{min} + 3\sigma`; if the start itself
     is not significantly above the minimum, do the same backwards. Steps stop at the cube's faces.
   * scan: add evenly spaced points over the bracket, fit a parabola to all samples on the line,
     drop outliers (residual beyond three times the larger of the noise :math:`\sigma` and the
     residuals' robust spread) and refit; measure at the fitted minimum. If the fit is not convex,
     or its measured minimum is significantly worse than the best sample, keep the best sample.

2. Powell's update: with :math:`u_0, f_0` the cycle's start, :math:`u_m, f_m` its end,
   :math:`\Delta` the largest single-direction decrease (direction :math:`k`) and
   :math:`f_e = f(2 u_m - u_0)` (projected into the cube), the new direction
   :math:`(u_m - u_0)/\lVert u_m - u_0 \rVert` replaces :math:`v_k` (and is line-minimized) unless

   .. math::

       f_e \ge f_0 \quad\text{or}\quad
       2 (f_0 - 2 f_m + f_e) (f_0 - f_m - \Delta)^2 \ge (f_0 - f_e)^2 \Delta,

   or the new set would be nearly singular.

Cycles repeat forever (there is no stopping test), so ``ask`` always has an answer. A cycle in
which no line search moved halves the initial step (down to ``MIN_STEP``): without it, a
noise-free run whose parabola fits miss a curved valley would repeat the same cycle forever. With
``noise=0`` the bracket stops at the first value above the minimum and the parabola fit is exact for
a quadratic, so the method converges like Powell's on smooth objectives.
"""

from __future__ import annotations

import numpy as np
import torch

from pigp_torch._utils import DTYPE
from pigp_torch.optimizers._coroutine import Coroutine, CoroutineOptimizer, feasible_interval

GOLDEN = (1.0 + 5.0**0.5) / 2.0
#: Step growth switches from geometric to additive at this length (normalized units).
MAX_GEOMETRIC_STEP = 0.1
#: Number of evenly spaced scan points across a bracket (ends included, some may be skipped).
N_SCAN = 6
#: Floor for the step, which is halved after every cycle in which no line search moved.
MIN_STEP = 1e-6
#: Smallest singular value accepted for the direction set after a replacement.
MIN_SINGULAR_VALUE = 1e-6


def _grow(step: float) -> float:
    return step * (1.0 + GOLDEN) if step < MAX_GEOMETRIC_STEP else step + MAX_GEOMETRIC_STEP


def fit_parabola_minimum(t: np.ndarray, f: np.ndarray, noise: float) -> float | None:
    r"""Minimizer of a least-squares parabola through line samples, with outlier rejection.

    Fits :math:`f \approx a t^2 + b t + c`, drops samples whose residual exceeds
    :math:`3 \max(\sigma, 1.4826\,\mathrm{MAD})` (MAD: median absolute deviation of the residuals),
    refits if at least three samples remain, and returns :math:`t^* = -b / (2a)`.

    Args:
        t: ``n`` step lengths along the line.
        f: ``n`` objective values (to minimize).
        noise: standard deviation :math:`\sigma` of the values.

    Returns:
        :math:`t^*` (not clipped), or ``None`` when there are fewer than three distinct samples,
        the values are flat, or the fitted parabola is not convex.
    """
    t = np.asarray(t, dtype=np.float64)
    f = np.asarray(f, dtype=np.float64)
    if np.unique(t).size < 3:
        return None
    with np.errstate(all="ignore"):
        # scale both axes to O(1) so huge or tiny values do not spoil the least-squares fit
        t_mid, t_half = 0.5 * (t.max() + t.min()), 0.5 * (t.max() - t.min())
        f_min, f_range = f.min(), f.max() - f.min()
        if not (np.isfinite(f_range) and f_range > 0.0):
            return None
        z, g = (t - t_mid) / t_half, (f - f_min) / f_range
        keep = np.ones(z.size, dtype=bool)
        for _ in range(2):  # fit, reject outliers, refit
            coef = np.linalg.lstsq(np.vander(z[keep], 3), g[keep], rcond=None)[0]
            residual = g - np.polyval(coef, z)
            r = residual[keep]
            spread = 1.4826 * np.median(np.abs(r - np.median(r)))
            threshold = 3.0 * max(spread, noise / f_range, 1e-9)
            new_keep = np.abs(residual) <= threshold
            if new_keep.sum() < 3 or np.unique(z[new_keep]).size < 3 or (new_keep == keep).all():
                break
            keep = new_keep
        a, b = coef[0], coef[1]
        if not (np.isfinite(a) and np.isfinite(b) and a > 0.0):
            return None
        t_star = t_mid - t_half * b / (2.0 * a)
    return float(t_star) if np.isfinite(t_star) else None


def line_minimize(
    u0: np.ndarray, f0: float, direction: np.ndarray, step: float, noise: float
) -> Coroutine:
    r"""Noise-robust minimization of :math:`f(u_0 + t v)` over :math:`t` (bracket, scan, fit).

    A generator coroutine: yields the points to measure and returns
    ``(u_min, f_min, n_evaluations)``.

    Args:
        u0: ``d`` start point in the unit cube, with measured value ``f0``.
        f0: objective value (to minimize) at ``u0``.
        direction: ``d`` unit direction :math:`v`.
        step: first step length along :math:`v`.
        noise: standard deviation :math:`\sigma` of the measurements; bracket ends must lie
            :math:`3\sigma` above the smallest value found.
    """
    t_min, t_max = feasible_interval(u0, direction)
    if t_max - t_min <= 1e-12:  # the line is blocked by the cube's faces both ways
        return u0, f0, 0
    threshold = 3.0 * noise
    samples = {0.0: f0}
    best_t, best_f = 0.0, f0

    # bracket: forward, then (if the start is not clearly above the minimum) backward
    t_hi, length = 0.0, step
    while t_hi < t_max:
        t_hi = min(length, t_max)
        f = yield u0 + t_hi * direction
        samples[t_hi] = f
        if f < best_f:
            best_t, best_f = t_hi, f
        if f > best_f + threshold:
            break
        length = _grow(length)
    t_lo, length = 0.0, step
    if not f0 > best_f + threshold:
        while t_lo > t_min:
            t_lo = max(-length, t_min)
            f = yield u0 + t_lo * direction
            samples[t_lo] = f
            if f < best_f:
                best_t, best_f = t_lo, f
            if f > best_f + threshold:
                break
            length = _grow(length)

    # scan: evenly spaced points over the bracket, skipping those next to existing samples
    grid = np.linspace(t_lo, t_hi, N_SCAN)
    spacing = (t_hi - t_lo) / (N_SCAN - 1)
    for t in grid:
        if min(abs(t - s) for s in samples) > spacing / 3.0:
            f = yield u0 + t * direction
            samples[float(t)] = f
            if f < best_f:
                best_t, best_f = float(t), f
    n_evaluations = len(samples) - 1

    # fit: move to the parabola's minimum if it is not clearly worse than the best sample
    ts = np.fromiter(samples.keys(), dtype=np.float64)
    fs = np.fromiter(samples.values(), dtype=np.float64)
    t_star = fit_parabola_minimum(ts, fs, noise)
    if t_star is not None:
        t_star = min(max(t_star, t_lo), t_hi)
        nearest = min(samples, key=lambda s: abs(s - t_star))
        if abs(nearest - t_star) > 1e-9:
            f_star = yield u0 + t_star * direction
            n_evaluations += 1
            if not f_star > best_f + threshold:
                return u0 + t_star * direction, f_star, n_evaluations
    return u0 + best_t * direction, best_f, n_evaluations


def powell_keeps_directions(f0: float, f_m: float, f_e: float, drop: float) -> bool:
    r"""Powell's test: ``True`` when the direction set should be kept unchanged.

    .. math::

        f_e \ge f_0 \quad\text{or}\quad
        2 (f_0 - 2 f_m + f_e) (f_0 - f_m - \Delta)^2 \ge (f_0 - f_e)^2 \Delta

    Args:
        f0: value at the start of the cycle.
        f_m: value at the end of the cycle.
        f_e: value at the extrapolated point :math:`2 u_m - u_0`.
        drop: largest decrease :math:`\Delta` achieved along a single direction in the cycle.
    """
    f0, f_m, f_e, drop = (np.float64(v) for v in (f0, f_m, f_e, drop))
    with np.errstate(all="ignore"):  # huge values overflow to inf; the comparisons still decide
        lhs = 2.0 * (f0 - 2.0 * f_m + f_e) * (f0 - f_m - drop) ** 2
        return bool(f_e >= f0 or lhs >= (f0 - f_e) ** 2 * drop)


def rcds(
    u0: np.ndarray, f0: float, *, noise: float, step: float, directions: np.ndarray
) -> Coroutine:
    r"""RCDS minimization in the unit cube, as a generator coroutine (``f = yield u``).

    Args:
        u0: ``d`` start point in :math:`[0, 1]^d`, measured value ``f0``.
        f0: objective value (to minimize) at ``u0``.
        noise: standard deviation of the measurements (objective units).
        step: initial step of each line search (normalized units).
        directions: ``d x d`` initial direction set, one unit direction per COLUMN.

    Yields:
        ``d`` points in the unit cube, each to be answered with its objective value via ``send``.
    """
    n = u0.size
    D = np.array(directions, dtype=np.float64)
    u_m, f_m = np.array(u0, dtype=np.float64), float(f0)
    while True:
        u_start, f_start = u_m.copy(), f_m
        largest_drop, k, n_cycle = 0.0, 0, 0
        for i in range(n):
            u_new, f_new, n_eval = yield from line_minimize(u_m, f_m, D[:, i], step, noise)
            n_cycle += n_eval
            if f_m - f_new > largest_drop:
                largest_drop, k = f_m - f_new, i
            u_m, f_m = np.clip(u_new, 0.0, 1.0), f_new
        if n_cycle == 0:  # every line blocked (start in a corner): the unit directions never are
            D = np.eye(n)
            continue

        shift = u_m - u_start
        norm = float(np.linalg.norm(shift))
        if norm <= 1e-12:  # no line moved: search closer (else a noise-free run repeats itself)
            step = max(0.5 * step, MIN_STEP)
            continue
        f_e = yield np.clip(u_m + shift, 0.0, 1.0)
        if powell_keeps_directions(f_start, f_m, f_e, largest_drop):
            continue
        new_direction = shift / norm
        candidate = np.column_stack([np.delete(D, k, axis=1), new_direction])
        if np.linalg.svd(candidate, compute_uv=False).min() < MIN_SINGULAR_VALUE:
            continue
        D = candidate
        u_new, f_new, _ = yield from line_minimize(u_m, f_m, new_direction, step, noise)
        u_m, f_m = np.clip(u_new, 0.0, 1.0), f_new


class RCDS(CoroutineOptimizer):
    r"""Robust Conjugate Direction Search (Huang et al. 2013), driven by ``ask``/``tell``.

    Args:
        bounds: ``2 x d`` knob bounds.
        noise: standard deviation :math:`\sigma` of the objective measurements (same units as
            ``y``); bracket ends must lie :math:`3\sigma` above the best value on the line. ``0``
            for a noise-free objective.
        step: initial step of each line search along a unit direction, in normalized units
            (fraction of the knob ranges), in :math:`(0, 1]`.
        directions: initial ``d x d`` direction set in normalized coordinates, one direction per
            column (normalized to unit length here); default the identity (one knob at a time).
        maximize: maximize (default) or minimize the objective.

    Example:
        >>> opt = RCDS(bounds, noise=0.04)
        >>> opt.tell(x0, measure(x0))
        >>> for _ in range(300):
        ...     x = opt.ask()
        ...     opt.tell(x, measure(x))
    """

    name = "rcds"

    def __init__(
        self,
        bounds,
        *,
        noise: float = 0.0,
        step: float = 0.05,
        directions=None,
        maximize: bool = True,
    ) -> None:
        super().__init__(bounds, maximize=maximize)
        noise, step = float(noise), float(step)
        if not (np.isfinite(noise) and noise >= 0.0):
            raise ValueError(f"noise must be a finite standard deviation >= 0, got {noise}")
        if not 0.0 < step <= 1.0:
            raise ValueError(f"step must lie in (0, 1], got {step}")
        d = self.dim
        if directions is None:
            D = np.eye(d)
        else:
            D = torch.as_tensor(directions, dtype=DTYPE).detach().cpu().numpy().copy()
            if D.shape != (d, d):
                raise ValueError(f"directions must have shape ({d}, {d}); got {D.shape}")
            if not np.isfinite(D).all():
                raise ValueError("directions contain NaN or inf")
            norms = np.linalg.norm(D, axis=0)
            if (norms == 0.0).any():
                raise ValueError("directions contain a zero column")
            D = D / norms
            if np.linalg.svd(D, compute_uv=False).min() < MIN_SINGULAR_VALUE:
                raise ValueError("directions must be linearly independent (full rank)")
        self.noise = noise
        self.step = step
        self.directions = D

    def _algorithm(self, u0: np.ndarray, f0: float) -> Coroutine:
        return rcds(u0, f0, noise=self.noise, step=self.step, directions=self.directions)
