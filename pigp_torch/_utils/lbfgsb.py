r"""L-BFGS-B with less per-evaluation overhead: scipy's compiled routine, driven directly.

:func:`scipy.optimize.minimize` (``method="L-BFGS-B"``) wraps the objective in several layers
(memoized value/gradient, a scalar-function object with array-API conversions, copies, finite
checks). Those layers add Python work to every evaluation, and the MAP fit evaluates the
objective several hundred times per ask (the overhead is measured in docs/results.md).
:func:`minimize_lbfgsb` runs the same compiled routine (``scipy.optimize._lbfgsb.setulb``) with
the same inputs, so the iterates, values and stopping are bit-identical to
:func:`scipy.optimize.minimize`; only the Python around it is thinner.

``setulb`` is private to scipy and its signature has changed between releases. So the direct
driver is used only after a self-check at first use: it must reproduce
:func:`scipy.optimize.minimize` bit for bit on a small bounded problem. If the routine is
missing, its signature differs, or the results differ in any bit, every call goes through
:func:`scipy.optimize.minimize` instead (same results, the old speed).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import scipy.optimize

__all__ = ["minimize_lbfgsb"]

FunAndGrad = Callable[[np.ndarray], tuple[float, np.ndarray]]

#: ``None`` before the first call; then whether the direct driver passed its self-check.
_DIRECT_OK: bool | None = None


def minimize_lbfgsb(
    fun_and_grad: FunAndGrad,
    x0,
    bounds=None,
    maxiter: int = 15000,
    maxfun: int = 15000,
    ftol: float = 2.2204460492503131e-09,
    gtol: float = 1e-5,
    maxcor: int = 10,
    maxls: int = 20,
) -> scipy.optimize.OptimizeResult:
    r"""Minimize ``fun_and_grad`` by L-BFGS-B; the same result as
    ``scipy.optimize.minimize(fun_and_grad, x0, jac=True, method="L-BFGS-B", bounds=bounds,
    options=dict(maxiter=..., maxfun=..., ftol=..., gtol=..., maxcor=..., maxls=...))``.

    Args:
        fun_and_grad: ``x`` (``n``, float64) → ``(value, gradient)`` (float, ``n``).
        x0: ``n`` start point.
        bounds: ``None`` or a sequence of ``n`` ``(low, high)`` pairs (``None`` or ±inf for
            no limit).
        maxiter, maxfun, ftol, gtol, maxcor, maxls: scipy's L-BFGS-B options, same defaults.

    Returns:
        An ``OptimizeResult`` with ``x``, ``fun``, ``jac``, ``nit``, ``nfev``, ``status``,
        ``success`` (the direct driver's result has no ``hess_inv``).
    """
    global _DIRECT_OK
    if _DIRECT_OK is None:
        _DIRECT_OK = _self_check()
    options = dict(maxiter=maxiter, maxfun=maxfun, ftol=ftol, gtol=gtol, maxcor=maxcor, maxls=maxls)
    if _DIRECT_OK:
        return _direct(fun_and_grad, x0, bounds, **options)
    return scipy.optimize.minimize(
        fun_and_grad, x0, jac=True, method="L-BFGS-B", bounds=bounds, options=options
    )


def _direct(fun_and_grad, x0, bounds, maxiter, maxfun, ftol, gtol, maxcor, maxls):
    """The iteration loop of scipy's ``_minimize_lbfgsb`` (scipy >= 1.15), without the wrappers.

    Bit-identity holds because every input of ``setulb`` is what scipy passes, and the
    objective sees the same points: scipy evaluates at each point ``setulb`` asks for, except
    a repeat of the last point, which it serves from its memo (so does this loop)."""
    from scipy.optimize import _lbfgsb

    x = np.array(x0, dtype=np.float64).ravel()  # a copy: setulb updates it in place
    n = x.shape[0]
    nbd = np.zeros(n, np.int32)
    low = np.zeros(n, np.float64)
    high = np.zeros(n, np.float64)
    if bounds is not None:
        if len(bounds) != n:
            raise ValueError("length of x0 != length of bounds")
        lb = np.array([-np.inf if lo is None else float(lo) for lo, _ in bounds])
        ub = np.array([np.inf if hi is None else float(hi) for _, hi in bounds])
        if (lb > ub).any():
            raise ValueError("L-BFGS-B: a lower bound is greater than its upper bound")
        x = np.clip(x, lb, ub)
        has_lo, has_hi = np.isfinite(lb), np.isfinite(ub)
        low[has_lo], high[has_hi] = lb[has_lo], ub[has_hi]
        # scipy's code: 0 unbounded, 1 lower only, 2 both, 3 upper only
        nbd[:] = np.where(has_lo, np.where(has_hi, 2, 1), np.where(has_hi, 3, 0))
    m = maxcor
    f = np.array(0.0, dtype=np.float64)
    g = np.zeros(n, dtype=np.float64)
    wa = np.zeros(2 * m * n + 5 * n + 11 * m * m + 8 * m, np.float64)
    iwa = np.zeros(3 * n, dtype=np.int32)
    task = np.zeros(2, dtype=np.int32)
    ln_task = np.zeros(2, dtype=np.int32)
    lsave = np.zeros(4, dtype=np.int32)
    isave = np.zeros(44, dtype=np.int32)
    dsave = np.zeros(29, dtype=np.float64)
    factr = ftol / np.finfo(float).eps
    last_x, last = None, None
    nfev = nit = 0
    while True:
        g = g.astype(np.float64)
        _lbfgsb.setulb(m, x, low, high, nbd, f, g, factr, gtol, wa, iwa, task, lsave, isave,
                       dsave, maxls, ln_task)  # fmt: skip
        if task[0] == 3:  # wants f and g at x
            if last_x is None or not np.array_equal(x, last_x):
                value, grad = fun_and_grad(x.copy())
                last_x, last = x.copy(), (_scalar(value), np.atleast_1d(grad))
                nfev += 1
            f, g = last
        elif task[0] == 1:  # a new iterate
            nit += 1
            if nit >= maxiter:
                task[0], task[1] = 5, 504
            elif nfev > maxfun:
                task[0], task[1] = 5, 502
        else:
            break
    status = 0 if task[0] == 4 else (1 if (nfev > maxfun or nit >= maxiter) else 2)
    return scipy.optimize.OptimizeResult(
        x=x, fun=f, jac=g, nit=nit, nfev=nfev, status=status, success=status == 0
    )


def _scalar(value) -> float:
    return value if np.isscalar(value) else np.asarray(value).item()


def _self_check() -> bool:
    """Whether :func:`_direct` reproduces :func:`scipy.optimize.minimize` bit for bit on a small
    bounded, badly scaled problem that hits its bounds (and on the same problem unbounded)."""
    rng = np.random.default_rng(0)
    A = rng.standard_normal((6, 6))
    A = A @ A.T + np.diag([1e-2, 1.0, 10.0, 1.0, 1e2, 1.0])
    b = rng.standard_normal(6)

    def fg(x):
        r = A @ x - b
        return float(0.5 * r @ r + np.sum(x**4)), A.T @ r + 4 * x**3

    x0 = np.full(6, 0.3)
    try:
        for bounds in ([(-0.2, 0.5)] * 5 + [(None, 0.1)], None):
            opts = dict(maxiter=50, maxfun=15000, ftol=1e-15, gtol=1e-11, maxcor=10, maxls=20)
            ref = scipy.optimize.minimize(fg, x0, jac=True, method="L-BFGS-B", bounds=bounds,
                                          options=opts)  # fmt: skip
            got = _direct(fg, x0, bounds, **opts)
            same = (
                np.array_equal(ref.x, got.x)
                and float(ref.fun) == float(got.fun)
                and (ref.nit, ref.nfev, ref.status) == (got.nit, got.nfev, got.status)
            )
            if not same:
                return False
    except Exception:  # a missing or changed private routine: use scipy's public path
        return False
    return True
