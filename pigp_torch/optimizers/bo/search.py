r"""The search part of the Bayesian-optimization core: maximize a bound acquisition in a box.

* :class:`NewtonSearch`: random points of the box scored in one batch, the best of them plus the
  given starts and the last proposals climbed together by the batched projected Newton method
  (:func:`maximize_in_unit_box`, needs Hessians) or as one stacked L-BFGS-B problem (gradients);
* :class:`MultiStartLBFGSB`: Sobol starts plus the given ones by batched L-BFGS-B
  (:func:`pigp_torch._utils.multistart.find_optimum`, gradients);
* :class:`OptimizeAcqf`: BoTorch's ``optimize_acqf`` on a BoTorch acquisition object.

Every search works in the unit cube of the box (:math:`\mathbf x = \boldsymbol\ell + \mathbf u
\odot (\mathbf h - \boldsymbol\ell)`), so the problem is well scaled whatever the knob units, and
returns ``(x: d, value, info)``.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from pigp_torch._utils import DTYPE
from pigp_torch._utils.lbfgsb import minimize_lbfgsb
from pigp_torch._utils.multistart import find_optimum
from pigp_torch.optimizers.bo.region import clamp_to_box

#: Solvers of :class:`NewtonSearch` and their default ``options``: the batched projected Newton
#: method (:func:`maximize_in_unit_box`) or scipy's L-BFGS-B on the stacked starts (BoTorch's
#: ``gen_candidates_scipy`` scheme; needed when the posterior has no Hessian).
SOLVER_DEFAULTS = {
    "newton": {"maxiter": 50, "gtol": 1e-7, "ftol": 1e-12},
    "lbfgsb": {"maxiter": 200, "ftol": 2.220446049250313e-09, "gtol": 1e-5, "maxcor": 10},
}
#: ``method="auto"`` uses Newton up to this many knobs: its Hessian costs :math:`O(n^2 d)` per
#: start, so at many knobs L-BFGS-B is the cheaper search.
NEWTON_MAX_DIM = 32
#: Damping multipliers tried at once in each round of :func:`maximize_in_unit_box`.
DAMPING_TRIALS = np.array([1.0, 4.0, 16.0, 64.0])


def maximize_in_unit_box(
    fun: Callable[..., tuple],
    U0: np.ndarray,
    *,
    maxiter: int = 50,
    gtol: float = 1e-7,
    ftol: float = 1e-12,
    max_trials: int = 40,
) -> tuple[np.ndarray, np.ndarray, dict]:
    r"""Batched projected Levenberg-Marquardt-Newton ascent of independent starts in
    :math:`[0,1]^d`.

    Each row of ``U0`` is one start; all rows move at once (one call of ``fun`` per round for all
    of them) but each has its own step and damping. Per start, with gradient :math:`\mathbf g`,
    Hessian :math:`H` and the binding set :math:`B = \{j: u_j \le \epsilon, g_j < 0\} \cup
    \{j: u_j \ge 1 - \epsilon, g_j > 0\}` (Bertsekas' projected Newton, :math:`\epsilon` = the
    projected-gradient norm, at most 1e-3), the step on the free coordinates
    :math:`F` is

    .. math:: \mathbf p_F = V (\max(\Lambda, 0) + \lambda I)^{-1} V^\top \mathbf g_F, \qquad
              -H_{FF} = V \Lambda V^\top,

    :math:`\mathbf p_B = 0`, and the trial point is :math:`\mathrm{clip}(\mathbf u +
    \mathbf p, 0, 1)`. Along concave directions this is a damped Newton step; along convex
    ones (at a data point the variance has a minimum) the damping alone sets the step, which
    grows while steps succeed, so a start escapes a convex region quickly. The damping
    :math:`\lambda` is adapted from the ratio :math:`\rho` of the actual to the predicted gain
    of the quadratic model (Levenberg-Marquardt, like a trust region): a trial with
    :math:`\rho < 10^{-4}` is rejected; an accepted one divides
    :math:`\lambda` by 4 when :math:`\rho > 0.75` and doubles it when :math:`\rho < 0.25`.
    Each round tries the dampings :math:`\lambda \cdot` :data:`DAMPING_TRIALS` in one batched
    evaluation and keeps the accepted trial of largest gain (a rejection of all of them
    multiplies :math:`\lambda` by 256).
    Near the optimum :math:`\lambda \to 0` (pure Newton, quadratic convergence). A start stops
    when its projected gradient :math:`\max_j |\mathrm{clip}(u_j + g_j, 0, 1) - u_j|` is below
    ``gtol``, when a step gains less than ``ftol`` :math:`(1 + |f|)`, or after ``max_trials``
    rejected trials in a row.

    Hand-written because scipy's L-BFGS-B (the starts stacked into one problem) needs 100-200
    iterations here and spends most of its time in per-call Python overhead; Newton steps with the
    closed-form Hessian converge in a few iterations, for all starts at once.

    Args:
        fun: ``fun(U: k x d, order)`` returning values (``order=0``) or ``(values, grads,
            hessians)`` (``order=2``) in unit-cube coordinates.
        U0: ``k x d`` starts (clipped into the cube).
        maxiter: accepted steps at most per start.
        gtol: projected-gradient tolerance.
        ftol: relative gain tolerance.
        max_trials: rejected trials in a row before a start gives up.

    Returns:
        ``(U, f, info)``: final points, their values and ``{"iterations", "evaluations"}``
        (accepted steps of the slowest start, batched calls of ``fun``).
    """
    s = _NewtonState(fun, U0)
    for _ in range(maxiter * (max_trials + 1)):
        pg = np.clip(s.U + s.g, 0.0, 1.0) - s.U
        s.active &= (np.abs(pg).max(1) > gtol) & (s.steps < maxiter) & (s.fails < max_trials)
        if not s.active.any():
            break
        idx = np.flatnonzero(s.active)
        e = idx[s.need_eig[idx]]
        if e.size:
            s.eigen(e, pg)
        s.trial_round(fun, idx, ftol)
    return s.U, s.f, {"iterations": int(s.steps.max(initial=0)), "evaluations": s.n_evals}


class _NewtonState:
    """The per-start state of :func:`maximize_in_unit_box` and its two steps."""

    def __init__(self, fun, U0: np.ndarray) -> None:
        self.U = np.clip(np.array(U0, dtype=np.float64), 0.0, 1.0)
        k, d = self.U.shape
        self.f, self.g, self.H = fun(self.U, 2)
        self.n_evals = 1
        self.steps = np.zeros(k, dtype=int)
        self.fails = np.zeros(k, dtype=int)
        self.damping = np.zeros(k)
        self.scale = np.ones(k)
        self.active = np.ones(k, dtype=bool)
        self.need_eig = np.ones(k, dtype=bool)
        self.lam = np.ones((k, d))
        self.V = np.zeros((k, d, d))
        self.Vg = np.zeros((k, d))
        self.free = np.ones((k, d), dtype=bool)
        self.diag = np.arange(d)

    def eigen(self, e: np.ndarray, pg: np.ndarray) -> None:
        """Eigen-decompose the reduced Hessian of starts ``e`` (once per accepted step)."""
        U, g, H, diag = self.U, self.g, self.H, self.diag
        # epsilon-binding set (Bertsekas): within eps of a bound and pushing against it
        eps = np.minimum(1e-3, np.abs(pg[e]).max(1))[:, None]
        fr = ~(((U[e] <= eps) & (g[e] < 0.0)) | ((U[e] >= 1.0 - eps) & (g[e] > 0.0)))
        M = -H[e] * (fr[:, :, None] & fr[:, None, :])
        M[:, diag, diag] += ~fr
        w, Ve = np.linalg.eigh(M)
        self.lam[e], self.V[e], self.free[e] = w, Ve, fr
        self.Vg[e] = np.einsum("kji,kj->ki", Ve, g[e] * fr)
        self.scale[e] = np.abs(w).max(1) + 1e-300
        self.damping[e] = np.where(self.steps[e] == 0, 1e-3 * self.scale[e], self.damping[e])
        self.need_eig[e] = False

    def trial_round(self, fun, idx: np.ndarray, ftol: float) -> None:
        """Try the dampings of :data:`DAMPING_TRIALS` for the active starts ``idx`` at once and
        accept or reject (Levenberg-Marquardt rule of :func:`maximize_in_unit_box`)."""
        U, f, g, H, damping = self.U, self.f, self.g, self.H, self.damping
        d = U.shape[1]
        # concave directions: damped Newton; convex ones (lam < 0): the damping alone. Several
        # dampings are tried at once (one batched evaluation instead of a round per rejection).
        a, m = idx.size, DAMPING_TRIALS.size
        denom = (
            np.maximum(self.lam[idx], 0.0)[:, None, :]
            + damping[idx, None, None] * DAMPING_TRIALS[None, :, None]
        )
        p = np.einsum("kij,kmj->kmi", self.V[idx], self.Vg[idx][:, None, :] / denom)
        p = p * self.free[idx][:, None]
        trial = np.clip(U[idx][:, None, :] + p, 0.0, 1.0)
        ft = fun(trial.reshape(a * m, d), 0).reshape(a, m)
        self.n_evals += 1
        step = trial - U[idx][:, None, :]
        quad = np.einsum("kmi,kij,kmj->km", step, H[idx], step)
        predicted = np.einsum("ki,kmi->km", g[idx], step) + 0.5 * quad
        actual = ft - f[idx][:, None]
        rho = np.where(predicted > 0, actual / np.where(predicted > 0, predicted, 1.0), -1.0)
        okm = (actual > 0) & (rho > 1e-4)
        best = np.argmax(np.where(okm, actual, -np.inf), axis=1)
        ok = okm[np.arange(a), best]
        acc, rej = idx[ok], idx[~ok]
        damping[rej] = np.maximum(4.0 * DAMPING_TRIALS[-1] * damping[rej], 1e-8 * self.scale[rej])
        self.fails[rej] += 1
        rho = rho[np.arange(a), best]
        actual = actual[np.arange(a), best]
        trial = trial[np.arange(a), best]
        ft = ft[np.arange(a), best]
        damping[acc] *= DAMPING_TRIALS[best[ok]]
        if acc.size:
            self._accept(fun, acc, rho[ok], actual[ok], trial[ok], ft[ok], ftol)

    def _accept(self, fun, acc, r, gain, trial, ft, ftol: float) -> None:
        """Move the starts ``acc`` to their accepted trials and adapt their damping."""
        damping = self.damping
        lower = 1e-12 * self.scale[acc]
        damping[acc] = np.where(r > 0.75, np.maximum(damping[acc] / 4, lower), damping[acc])
        damping[acc] = np.where(r < 0.25, 2.0 * damping[acc], damping[acc])
        small_gain = gain <= ftol * (1.0 + np.abs(self.f[acc]))
        self.U[acc] = trial
        self.fails[acc] = 0
        self.steps[acc] += 1
        self.active[acc[small_gain]] = False
        go = acc[~small_gain]
        if go.size:
            self.f[go], self.g[go], self.H[go] = fun(self.U[go], 2)
            self.n_evals += 1
            self.need_eig[go] = True
        self.f[acc[small_gain]] = ft[small_gain]


def _maximize_lbfgsb(fun, U0: np.ndarray, options: dict):
    """All starts as one L-BFGS-B problem on the sum of their values (BoTorch's scheme)."""
    k, d = U0.shape
    count = {"n": 0}

    def neg_total(uflat: np.ndarray) -> tuple[float, np.ndarray]:
        value, g = fun(uflat.reshape(k, d), 1)
        count["n"] += 1
        return -float(value.sum()), -g.reshape(-1)

    res = minimize_lbfgsb(neg_total, U0.reshape(-1), bounds=[(0.0, 1.0)] * (k * d), **options)
    U = np.clip(res.x.reshape(k, d), 0.0, 1.0)
    return U, fun(U, 0), {"iterations": int(res.nit), "evaluations": count["n"] + 1}


class NewtonSearch:
    r"""Random points, then Newton (or stacked L-BFGS-B) from the best of them and given starts.

    ``raw_samples`` uniform random points of the box (from ``numpy.random.default_rng(seed)``)
    are scored in one batch; the ``num_restarts`` best of them, the given starts and the last
    ``n_previous`` proposals of this search (clipped into the box; duplicates dropped) are
    climbed; the best point among the climbed starts and the raw samples is returned.

    Args:
        num_restarts: best random points kept as starts (>= 0).
        raw_samples: random points scored (>= ``num_restarts``).
        method: ``"newton"``, ``"lbfgsb"`` or ``"auto"`` (Newton when the posterior gives
            Hessians and there are at most :data:`NEWTON_MAX_DIM` knobs).
        options: solver options over :data:`SOLVER_DEFAULTS` of the method.
        n_previous: earlier proposals used as extra starts.
    """

    def __init__(self, num_restarts=10, raw_samples=256, method="auto", options=None,
                 n_previous: int = 2):  # fmt: skip
        if int(num_restarts) < 0 or int(raw_samples) < int(num_restarts):
            raise ValueError(
                "need num_restarts >= 0 and raw_samples >= num_restarts; "
                f"got {num_restarts}, {raw_samples}"
            )
        if method not in ("auto", *SOLVER_DEFAULTS):
            raise ValueError(f"method must be 'auto', 'newton' or 'lbfgsb', got {method!r}")
        self.options = dict(options or {})
        known = set().union(*SOLVER_DEFAULTS.values()) if method == "auto" else None
        known = known or set(SOLVER_DEFAULTS[method])
        unknown = sorted(set(self.options) - known)
        if unknown:
            raise ValueError(
                f"unknown options {unknown} for method {method!r}; known: {sorted(known)}"
            )
        self.num_restarts, self.raw_samples = int(num_restarts), int(raw_samples)
        self.method, self.n_previous = method, int(n_previous)
        self.proposals: list[torch.Tensor] = []

    def solver(self, max_order: int, dim: int) -> str:
        """The solver used for a posterior of ``max_order`` derivatives in ``dim`` knobs."""
        if self.method != "auto":
            return self.method
        return "lbfgsb" if max_order < 2 or dim > NEWTON_MAX_DIM else "newton"

    def maximize(self, fun, box: torch.Tensor, starts, seed: int, max_order: int):
        """Maximize ``fun(X, order)`` in ``box`` (see the class docstring)."""
        d = box.shape[1]
        lo, width = box[0].numpy(), (box[1] - box[0]).numpy()

        def to_unit(x: torch.Tensor) -> np.ndarray:
            return np.clip((x.numpy() - lo) / width, 0.0, 1.0)

        def unit_fun(U: np.ndarray, order: int):
            out = fun(lo + U * width, order)
            if order == 0:
                return out
            if order == 1:
                return out[0], out[1] * width
            return out[0], out[1] * width, out[2] * width[:, None] * width[None, :]

        U_starts = [to_unit(s)[None] for s in starts]
        previous = self.proposals[max(0, len(self.proposals) - self.n_previous) :]
        U_starts += [to_unit(p)[None] for p in previous[::-1]]
        raw, raw_values, n_evals = np.empty((0, d)), np.empty(0), 0
        if self.raw_samples:
            # uniform points from a fresh seeded generator (cheaper than a scrambled SobolEngine)
            raw = np.random.default_rng(seed).random((self.raw_samples, d))
            raw_values = fun(lo + raw * width, 0)
            n_evals += 1
            if self.num_restarts:
                top = np.argsort(-raw_values, kind="stable")[: self.num_restarts]
                U_starts.append(raw[top])
        U0 = np.unique(np.concatenate(U_starts), axis=0)
        solver = self.solver(max_order, d)
        opts = {
            **SOLVER_DEFAULTS[solver],
            **{k: v for k, v in self.options.items() if k in SOLVER_DEFAULTS[solver]},
        }
        if solver == "newton":
            U, values, info = maximize_in_unit_box(unit_fun, U0, **opts)
        else:
            U, values, info = _maximize_lbfgsb(unit_fun, U0, opts)
        cand, cand_values = np.concatenate([U, raw]), np.concatenate([values, raw_values])
        i = int(np.argmax(cand_values))
        x = clamp_to_box(box[0] + torch.from_numpy(cand[i].copy()) * (box[1] - box[0]), box)
        self.proposals.append(x.clone())
        info = {"n_starts": U0.shape[0], "n_evals": n_evals + info["evaluations"],
                "iterations": info["iterations"], "solver": solver}  # fmt: skip
        return x, float(cand_values[i]), info


class MultiStartLBFGSB:
    """``n_starts`` Sobol points (scrambled with ``seed``) plus the given starts, climbed by
    batched L-BFGS-B with the closed-form gradient
    (:func:`~pigp_torch._utils.multistart.find_optimum`).

    Args:
        n_starts: Sobol starts (>= 0).
        maxiter: L-BFGS-B iterations.
    """

    def __init__(self, n_starts: int = 8, maxiter: int = 200) -> None:
        if int(n_starts) < 0:
            raise ValueError(f"n_starts must be >= 0, got {n_starts}")
        self.n_starts, self.maxiter = int(n_starts), int(maxiter)

    def maximize(self, fun, box: torch.Tensor, starts, seed: int, max_order: int):
        def with_grad(Z: torch.Tensor):
            value, grad = fun(Z.detach().numpy(), 1)
            return torch.from_numpy(value), torch.from_numpy(np.ascontiguousarray(grad))

        x, value = find_optimum(with_grad, box, n_starts=self.n_starts, seed=seed,
                                x_init=torch.stack(starts), maxiter=self.maxiter,
                                with_grad=True)  # fmt: skip
        return x, value, {}


class OptimizeAcqf:
    """BoTorch's ``optimize_acqf`` (``num_restarts`` L-BFGS-B restarts from ``raw_samples``
    Sobol points, extra ``options``) on a BoTorch acquisition object in the box's unit cube."""

    #: BoTorch draws from torch's global RNG: the core seeds a forked one per ask.
    uses_torch_rng = True

    def __init__(self, num_restarts: int = 4, raw_samples: int = 128, options=None) -> None:
        if int(num_restarts) < 1 or int(raw_samples) < int(num_restarts):
            raise ValueError(
                "need num_restarts >= 1 and raw_samples >= num_restarts; "
                f"got {num_restarts}, {raw_samples}"
            )
        self.num_restarts, self.raw_samples = int(num_restarts), int(raw_samples)
        self.options = dict(options or {})

    def maximize(self, acq, box: torch.Tensor, starts, seed: int, max_order: int):
        from botorch.optim import optimize_acqf

        d = box.shape[1]
        unit = torch.stack([torch.zeros(d, dtype=DTYPE), torch.ones(d, dtype=DTYPE)])
        u, value = optimize_acqf(_box_acquisition(acq, box[0], box[1]), bounds=unit, q=1,
                                 num_restarts=self.num_restarts, raw_samples=self.raw_samples,
                                 options=self.options)  # fmt: skip
        x = box[0] + u.detach().reshape(-1).clamp(0.0, 1.0) * (box[1] - box[0])
        return x, float(value.detach().reshape(-1)[0]), {}


def _box_acquisition(acq, lower: torch.Tensor, upper: torch.Tensor):
    r"""``acq`` seen through the map of the unit cube onto a box,
    :math:`\tilde a(u) = a(\ell + u \odot (h - \ell))`."""
    from botorch.acquisition import AcquisitionFunction

    class BoxAcquisition(AcquisitionFunction):
        def __init__(self) -> None:
            super().__init__(model=acq.model)
            self.acq = acq
            self.register_buffer("lower", lower)
            self.register_buffer("width", upper - lower)

        def forward(self, U: torch.Tensor) -> torch.Tensor:
            return self.acq(self.lower + U * self.width)

    return BoxAcquisition()
