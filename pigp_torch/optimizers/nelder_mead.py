r"""Nelder–Mead simplex search as an ask/tell optimizer.

Why our own implementation: :func:`scipy.optimize.minimize` (``method="Nelder-Mead"``) drives the
objective itself through a callback and cannot pause between evaluations for a machine that takes
seconds to settle, nor resume from a measurement reported later. Here the algorithm is a plain
generator coroutine (:mod:`pigp_torch.optimizers._coroutine`) that yields each point it wants
measured, so the same straight-line algorithm serves ``ask``/``tell``.

The search runs in the unit cube :math:`u = (x - x_{lo}) / (x_{hi} - x_{lo})`. Reflection and
expansion points that leave the cube are projected onto it (clipped); contractions and shrinks are
convex combinations of vertices and stay inside. Coefficients (reflection :math:`\alpha`, expansion
:math:`\gamma`, contraction :math:`\rho`, shrink :math:`\sigma`) are the classical
:math:`(1, 2, \tfrac12, \tfrac12)` or, with ``adaptive=True`` and :math:`d \ge 2`, those of
Gao & Han (Comput. Optim. Appl. 51 (2012) 259), which keep the method effective in higher
dimension:

.. math::

    \alpha = 1,\quad \gamma = 1 + \frac{2}{d},\quad \rho = \frac34 - \frac{1}{2d},\quad
    \sigma = 1 - \frac1d.

Restarts: when the simplex has converged (every vertex within ``xatol`` of the best one in every
normalized coordinate, and the spread of values at most ``fatol``), the best vertex is measured
once more and a fresh simplex of the initial size is built around it. The optimizer therefore
never stops asking. The fresh measurement matters on a noisy objective: a simplex tends to collapse
around a vertex whose value was lucky (the noise made it look better than it is); re-measuring it
lets the restarted simplex move on.
"""

from __future__ import annotations

import math

import numpy as np

from pigp_torch.optimizers._coroutine import Coroutine, CoroutineOptimizer


def nelder_mead(
    u0: np.ndarray,
    f0: float,
    *,
    size: float,
    adaptive: bool,
    xatol: float,
    fatol: float,
) -> Coroutine:
    r"""Nelder–Mead minimization in the unit cube, as a generator coroutine (``f = yield u``).

    Args:
        u0: ``d`` start point in :math:`[0, 1]^d`.
        f0: objective value (to minimize) at ``u0``.
        size: step of each initial vertex along its coordinate, in :math:`(0, \tfrac12]`; the step
            goes towards the side of the cube with more room so the vertex stays inside.
        adaptive: use the dimension-dependent coefficients of Gao & Han (for :math:`d \ge 2`).
        xatol: convergence when :math:`\max_{j,i} |u_{j,i} - u_{0,i}| \le` ``xatol``.
        fatol: ... and :math:`\max_j |f_j - f_0| \le` ``fatol`` (``inf``: size test only).

    Yields:
        ``d`` points in the unit cube, each to be answered with its objective value via ``send``.
    """
    n = u0.size
    if adaptive and n >= 2:
        alpha, gamma, rho, sigma = 1.0, 1.0 + 2.0 / n, 0.75 - 0.5 / n, 1.0 - 1.0 / n
    else:
        alpha, gamma, rho, sigma = 1.0, 2.0, 0.5, 0.5

    best_u, best_f = np.array(u0, dtype=np.float64), float(f0)
    while True:  # each pass builds a fresh simplex around the best point found so far
        V = np.tile(best_u, (n + 1, 1))
        F = np.empty(n + 1)
        F[0] = best_f
        for i in range(n):
            V[i + 1, i] += size if best_u[i] <= 0.5 else -size
            F[i + 1] = yield V[i + 1].copy()

        while True:
            order = np.argsort(F, kind="stable")
            V, F = V[order], F[order]
            with np.errstate(over="ignore"):  # values near the float limit: spread = inf
                converged = np.max(np.abs(V[1:] - V[0])) <= xatol and (
                    np.max(np.abs(F[1:] - F[0])) <= fatol
                )
            if converged:
                break
            centroid = V[:-1].mean(axis=0)
            u_r = np.clip(centroid + alpha * (centroid - V[-1]), 0.0, 1.0)
            f_r = yield u_r.copy()
            if f_r < F[0]:  # best so far: try going further
                u_e = np.clip(centroid + alpha * gamma * (centroid - V[-1]), 0.0, 1.0)
                f_e = yield u_e.copy()
                V[-1], F[-1] = (u_e, f_e) if f_e < f_r else (u_r, f_r)
            elif f_r < F[-2]:  # better than the second worst: accept the reflection
                V[-1], F[-1] = u_r, f_r
            else:
                if f_r < F[-1]:  # outside contraction, towards the reflected point
                    u_c = centroid + rho * (u_r - centroid)
                    f_c = yield u_c.copy()
                    accept = f_c <= f_r
                else:  # inside contraction, towards the worst vertex
                    u_c = centroid + rho * (V[-1] - centroid)
                    f_c = yield u_c.copy()
                    accept = f_c < F[-1]
                if accept:
                    V[-1], F[-1] = u_c, f_c
                else:  # shrink every vertex towards the best one
                    for j in range(1, n + 1):
                        V[j] = V[0] + sigma * (V[j] - V[0])
                        F[j] = yield V[j].copy()
        best_u = V[0].copy()
        best_f = yield best_u.copy()  # fresh value: a lucky noisy one must not anchor the restart


class NelderMead(CoroutineOptimizer):
    r"""Nelder–Mead simplex optimizer with restarts, driven by ``ask``/``tell``.

    The first ``tell(x0, y0)`` is the first vertex; the next ``d`` asks build the initial simplex
    by moving one knob each by ``initial_simplex_size`` times its range.

    Args:
        bounds: ``2 x d`` knob bounds.
        initial_simplex_size: initial step along each knob as a fraction of the knob's range,
            in :math:`(0, \tfrac12]`; also the size of each restarted simplex.
        maximize: maximize (default) or minimize the objective.
        adaptive: Gao–Han dimension-dependent coefficients (default) instead of the classical ones.
        xatol: convergence (then restart) when all vertices are within ``xatol`` (fraction of each
            knob's range) of the best vertex ...
        fatol: ... and their objective values within ``fatol`` of the best value (objective units;
            default ``inf``: the size test alone, since noisy measurements never agree to a fixed
            tolerance).

    Example:
        >>> opt = NelderMead(torch.tensor([[-1.0, -1.0], [1.0, 1.0]]))
        >>> opt.tell(torch.zeros(2), f(torch.zeros(2)))
        >>> for _ in range(100):
        ...     x = opt.ask()
        ...     opt.tell(x, f(x))
    """

    name = "nelder-mead"

    def __init__(
        self,
        bounds,
        *,
        initial_simplex_size: float = 0.05,
        maximize: bool = True,
        adaptive: bool = True,
        xatol: float = 1e-4,
        fatol: float = math.inf,
    ) -> None:
        super().__init__(bounds, maximize=maximize)
        size = float(initial_simplex_size)
        if not 0.0 < size <= 0.5:
            raise ValueError(f"initial_simplex_size must lie in (0, 0.5], got {size}")
        if not float(xatol) >= 0.0:
            raise ValueError(f"xatol must be >= 0, got {xatol}")
        if not float(fatol) >= 0.0:
            raise ValueError(f"fatol must be >= 0, got {fatol}")
        self.initial_simplex_size = size
        self.adaptive = bool(adaptive)
        self.xatol = float(xatol)
        self.fatol = float(fatol)

    def _algorithm(self, u0: np.ndarray, f0: float) -> Coroutine:
        return nelder_mead(
            u0,
            f0,
            size=self.initial_simplex_size,
            adaptive=self.adaptive,
            xatol=self.xatol,
            fatol=self.fatol,
        )
