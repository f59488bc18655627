r"""The least-squares solvers of :class:`~pigp_torch.optimizers.model_fit.FittedModelOptimizer`:
the fit of the unknowns (:func:`fit_unknowns`, Levenberg–Marquardt) and the two searches of its
ask, in a box and from several starts at once (:func:`least_squares_in_box`, a projected
Levenberg–Marquardt on residuals; :func:`minimize_in_box`, L-BFGS-B on a scalar goal stopped at
a stated fraction of the noise)."""

from __future__ import annotations

import math
from collections.abc import Callable

import torch

from pigp_torch._utils import DTYPE
from pigp_torch._utils.lbfgsb import minimize_lbfgsb


def row_jacobian(
    model: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
    X: torch.Tensor,
    theta: torch.Tensor,
    *,
    batched: bool | None = None,
    n_obs: int | None = None,
) -> torch.Tensor:
    r"""``N x m x P``: :math:`\partial M(x_n, \theta)_j / \partial \theta` of a model that acts
    row by row.

    Each row's observables depend on that row's setting and the unknowns only, so the model is
    evaluated once on the ``m N`` rows of ``X`` repeated ``m`` times, each row with its own copy
    of ``theta`` (``m N x P``), and the sum of observable ``j`` over the ``j``-th copy has row
    ``n``'s gradient in copy ``n`` of ``theta``: one backward pass. Reverse mode, so it also works
    where forward-mode autograd does not (complex intermediates such as the square root of a
    quadrupole's strength, when an unknown scales it).

    A model written for one vector of unknowns (``theta[k]`` rather than ``theta[..., k]``)
    cannot take a batch of them: with ``batched=None`` (default) :func:`takes_batched_unknowns`
    checks, and where it cannot (``batched=False``) the Jacobian is forward-mode autograd's.
    ``batched=True`` skips the check (a caller that checked once for its model and rows);
    ``n_obs``: the model's ``m`` when the caller knows it (else one model call finds it).
    """
    theta = theta.detach()
    if batched is None:
        batched = takes_batched_unknowns(model, X, theta)
    if not batched:
        return torch.autograd.functional.jacobian(
            lambda t: model(X, t), theta, strategy="forward-mode", vectorize=True
        ).detach()
    N = X.shape[0]
    if n_obs is None:
        with torch.no_grad():
            n_obs = model(X[:1], theta).shape[-1]
    m = int(n_obs)
    T = theta.expand(m * N, -1).clone().requires_grad_(True)
    with torch.enable_grad():
        out = model(X.repeat(m, 1), T)
    picked = out.reshape(m, N, m).diagonal(dim1=0, dim2=2)  # N x m: copy j, observable j
    (grad,) = torch.autograd.grad(picked.sum(), T)
    return grad.reshape(m, N, -1).permute(1, 0, 2)


def takes_batched_unknowns(
    model: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
    X: torch.Tensor,
    theta: torch.Tensor,
) -> bool:
    """Whether ``model`` takes an ``m N x P`` batch of unknowns row by row with ``X`` repeated
    ``m`` times: the batched call must not fail and must reproduce ``model(X, theta)`` in every
    copy (to 1e-9 relative)."""
    theta = theta.detach()
    with torch.no_grad():
        base = model(X, theta)
        m, N = base.shape[-1], X.shape[0]
        try:
            out = model(X.repeat(m, 1), theta.expand(m * N, -1))
            copies = out.reshape(m, N, m)
        except (RuntimeError, IndexError, ValueError):
            return False
    scale = float(base.abs().max()) if base.numel() else 0.0
    return bool(torch.allclose(copies, base.expand(m, N, m), rtol=1e-9, atol=1e-12 * scale))


def fit_unknowns(
    model: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
    X: torch.Tensor,
    O: torch.Tensor,
    center: torch.Tensor,
    half_width: torch.Tensor,
    *,
    obs_sd: float,
    prior_sd: float,
    u0: torch.Tensor | None = None,
    max_iter: int = 20,
    tol: float = 1e-8,
    weights: torch.Tensor | None = None,
    cost_tol: float = 0.0,
) -> tuple[torch.Tensor, float]:
    r"""Levenberg–Marquardt fit of the normalized unknowns (module docstring, step 1), with the
    Jacobian of :func:`row_jacobian`.

    Args:
        model: ``(N x d knobs, P unknowns) -> N x m`` observables, differentiable in the unknowns.
        X: ``N x d`` settings; O: ``N x m`` observables read there.
        center, half_width: ``P`` each; :math:`\theta = c + h \odot u`.
        obs_sd: observation noise :math:`s` (observable units); prior_sd: :math:`\sigma_u`.
        u0: ``P`` start (default zeros, the prior mean).
        max_iter: LM iterations; tol: stop when the cost changes by less than ``tol`` (relative)
            or by less than ``cost_tol`` (absolute, default 0).
        weights: ``N`` numbers of readings merged into each row of ``O`` (their mean; default
            ones): row ``k``'s squared residual counts ``weights[k]`` times, which is the same
            least-squares problem as the unmerged readings (up to a constant, their scatter).

    Returns:
        ``(u, cost)``: the fitted ``P`` normalized unknowns and the cost (the objective above).
    """
    P = center.numel()
    u = torch.zeros(P, dtype=DTYPE) if u0 is None else u0.detach().clone()

    w = torch.ones(X.shape[0], dtype=DTYPE) if weights is None else weights.to(DTYPE)
    root_w = w.sqrt().unsqueeze(-1)

    def residual(v: torch.Tensor) -> torch.Tensor:
        pred = model(X, center + half_width * v)
        return torch.cat([(root_w * (O - pred) / obs_sd).reshape(-1), v / prior_sd])

    r = residual(u).detach()
    cost = float(r @ r)
    eye = torch.eye(P, dtype=DTYPE)
    batched = None
    lam = 1e-3
    for _ in range(int(max_iter)):
        theta = center + half_width * u
        if batched is None:  # checked once per fit: the model and the rows do not change
            batched = takes_batched_unknowns(model, X, theta)
        dpred = row_jacobian(model, X, theta, batched=batched, n_obs=O.shape[-1])  # N x m x P
        dpred = dpred * half_width
        J = torch.cat([-(root_w.unsqueeze(-1) * dpred / obs_sd).reshape(-1, P), eye / prior_sd])
        A = J.T @ J
        g = J.T @ r
        improved = False
        for _ in range(10):
            step = torch.linalg.solve(A + lam * torch.diag(A.diagonal() + 1e-12), -g)
            r_new = residual(u + step).detach()
            c_new = float(r_new @ r_new)
            if math.isfinite(c_new) and c_new < cost:
                improved = True
                break
            lam *= 10.0
        if not improved:
            break
        drop = cost - c_new
        u, r, cost = u + step, r_new, c_new
        lam = max(lam / 10.0, 1e-9)
        if drop < tol * (cost + drop) or drop < cost_tol:
            break
    return u, cost


def fit_with_restarts(
    model: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
    X: torch.Tensor,
    O: torch.Tensor,
    center: torch.Tensor,
    half_width: torch.Tensor,
    *,
    u0: torch.Tensor,
    max_iter: int,
    restarts: int,
    restart_above: float,
    seed: int,
    **options,
) -> tuple[torch.Tensor, float, bool]:
    r""":func:`fit_unknowns` warm-started at ``u0``; when its cost per observable number exceeds
    ``restart_above`` (squared noise units: the model misses the readings by more than
    :math:`\sqrt{\text{restart\_above}}` noise sd on average), Levenberg–Marquardt may be stuck
    in a poor local minimum of the warm start, and the fit is repeated from the prior mean and
    from ``restarts - 1`` Sobol draws (seed ``seed``) of the unknowns' ranges
    (:math:`u \in [-1, 1]^P`), each with ``3 max_iter`` iterations; the lowest cost is kept.

    ``options``: the other keyword arguments of :func:`fit_unknowns`. Returns ``(u, cost,
    restarted)``.
    """

    def fit(start: torch.Tensor, iters: int) -> tuple[torch.Tensor, float]:
        return fit_unknowns(model, X, O, center, half_width, u0=start, max_iter=iters, **options)

    u, cost = fit(u0, max_iter)
    if restarts == 0 or cost <= restart_above * O.numel():
        return u, cost, False
    P = center.numel()
    starts = [torch.zeros(P, dtype=DTYPE)]
    if restarts > 1:
        sobol = torch.quasirandom.SobolEngine(P, scramble=True, seed=int(seed))
        starts += list(2 * sobol.draw(restarts - 1, dtype=DTYPE) - 1)
    for start in starts:
        u_k, cost_k = fit(start, 3 * max_iter)
        if cost_k < cost:
            u, cost = u_k, cost_k
    return u, cost, True


def least_squares_in_box(
    residual: Callable[[torch.Tensor], torch.Tensor],
    box: torch.Tensor,
    Z0: torch.Tensor,
    *,
    scale: float,
    max_iter: int,
    tol: float = 1e-3,
    abs_tol: float = 1e-2,
) -> torch.Tensor:
    r"""Projected Levenberg–Marquardt on :math:`\|r(x)\|^2 / s^2` inside ``box`` from each of the
    ``k`` unit-cube starts ``Z0`` at once; returns the ``k x d`` end points (unit cube).

    ``residual``: ``k x d`` settings ``->`` ``k x r`` residuals. Per iteration one batched
    evaluation of the Jacobian (each start repeated ``r`` times, one backward pass) and one of
    the trial steps; each start keeps its own damping :math:`\lambda` and accepts a step (clipped
    to the box) only when its sum of squares decreases. Stops after ``max_iter`` iterations or
    when no start improves by more than ``tol`` (relative) and ``abs_tol`` (absolute, in squared
    noise units: the end points agree with the optimum far below the noise).
    """
    lo, width = box[0], (box[1] - box[0]).clamp_min(1e-300)
    Z = Z0.detach().to(DTYPE).clone()
    k, d = Z.shape

    def res(z: torch.Tensor) -> torch.Tensor:
        return residual(lo + width * z) / scale

    with torch.no_grad():
        r = res(Z)
    m = r.shape[-1]
    cost = r.square().sum(-1)
    cost = torch.where(torch.isfinite(cost), cost, torch.full_like(cost, torch.inf))
    lam = torch.full((k,), 1e-3, dtype=DTYPE)
    eye = torch.eye(d, dtype=DTYPE)
    for _ in range(int(max_iter)):
        zr = Z.repeat_interleave(m, 0).requires_grad_(True)
        out = res(zr).reshape(k, m, m)
        (g,) = torch.autograd.grad(out.diagonal(dim1=1, dim2=2).sum(), zr)
        J = g.reshape(k, m, d)
        J = torch.where(torch.isfinite(J), J, torch.zeros_like(J))
        A = J.transpose(1, 2) @ J
        b = (J.transpose(1, 2) @ torch.nan_to_num(r).unsqueeze(-1)).squeeze(-1)
        diag = A.diagonal(dim1=1, dim2=2)
        damp = lam[:, None, None] * (torch.diag_embed(diag) + 1e-9 * diag.mean(-1)[:, None, None])
        step = torch.linalg.solve(A + damp + 1e-300 * eye, -b)
        Zn = (Z + step).clamp(0.0, 1.0)
        with torch.no_grad():
            rn = res(Zn)
        cn = rn.square().sum(-1)
        better = torch.isfinite(cn) & (cn < cost)
        drop = torch.where(better, cost - cn, torch.zeros_like(cn))
        moving = better & (drop > tol * cost) & (drop > abs_tol)
        Z = torch.where(better[:, None], Zn, Z)
        r = torch.where(better[:, None], rn, r)
        cost = torch.where(better, cn, cost)
        lam = torch.where(better, (lam / 10).clamp_min(1e-12), (lam * 10).clamp_max(1e12))
        if bool(better.any()) and not bool(moving.any()):
            break  # the improving starts have converged
        if not bool(better.any()) and bool((lam >= 1e12).all()):
            break  # no start can improve any more
    return Z


def minimize_in_box(
    goal: Callable[[torch.Tensor], torch.Tensor],
    box: torch.Tensor,
    Z0: torch.Tensor,
    *,
    scale: float,
    maxiter: int,
    ftol: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    r"""Minimize a batched ``goal`` (``k x d -> k``) inside ``box`` from ``k`` unit-cube starts
    ``Z0``, all starts as one L-BFGS-B problem on the sum of ``goal / scale`` (each row follows
    its own path; one batched evaluation per iteration).

    Hand-driven rather than :func:`~pigp_torch._utils.multistart.maximize_from` for its stopping
    rule: that one runs to machine precision (``ftol`` 1e-15), while the ask only needs the
    optimum to a small fraction of the noise; in units of ``scale`` (the noise), ``ftol`` is an
    absolute change of the summed goal below which the search stops.

    Returns:
        ``(X, values)``: ``k x d`` end points (knob units) and their goal values
        (``inf`` where not finite).
    """
    lo, width = box[0], (box[1] - box[0]).clamp_min(1e-300)
    k, d = Z0.shape

    def fun(zflat):
        z = torch.from_numpy(zflat.reshape(k, d)).to(DTYPE).requires_grad_(True)
        y = goal(lo + width * z) / scale
        ok = torch.isfinite(y)
        total = torch.where(ok, y, torch.zeros_like(y)).sum()
        (g,) = torch.autograd.grad(total, z)
        return float(total.detach()) + 1e6 * float((~ok).sum()), g.detach().numpy().reshape(-1)

    res = minimize_lbfgsb(
        fun,
        Z0.detach().to(DTYPE).numpy().reshape(-1),
        bounds=[(0.0, 1.0)] * (k * d),
        maxiter=maxiter,
        maxfun=2 * maxiter,
        ftol=ftol,
        gtol=1e-9,
    )
    X = lo + width * torch.from_numpy(res.x.reshape(k, d)).to(DTYPE)
    with torch.no_grad():
        v = goal(X)
    return X, torch.where(torch.isfinite(v), v, torch.full_like(v, torch.inf))


def search_in_box(
    goal: Callable[[torch.Tensor], torch.Tensor],
    residual: Callable[[torch.Tensor], torch.Tensor] | None,
    box: torch.Tensor,
    starts: torch.Tensor,
    *,
    scale: float,
    ls_iter: int,
    n_polish: int,
    polish_tol: float,
    maxiter: int,
    ftol: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    r"""The ask's search from ``k x d`` unit-cube ``starts`` in ``box``: ``(X, values)``, the
    end points (settings) and their goals.

    With ``residual`` (``N x d -> N x r``, zero at the goal's optimum): least squares first
    (:func:`least_squares_in_box`; the goal is small where the residuals are, and Gauss–Newton
    converges in a few iterations where a quasi-Newton search on a sum of absolute values crawls
    along its kinks), then the ``n_polish`` best end points polished by L-BFGS-B on the goal
    (:func:`minimize_in_box`) unless the best goal is already at most ``polish_tol`` ``scale``
    units (a target it reached needs no more); the least-squares end points compete as they are.
    Without ``residual``: L-BFGS-B from every start.
    """
    lo, width = box[0], box[1] - box[0]
    ls_starts = None
    if residual is not None:
        ends = least_squares_in_box(residual, box, starts, scale=scale, max_iter=ls_iter)
        with torch.no_grad():
            ls_values = goal(lo + width * ends)
        ls_starts = ends[torch.argsort(ls_values)]
        reached = bool(ls_values.min() <= polish_tol * scale)
        starts = ls_starts[: 0 if reached else n_polish]
    X, v = lo + width * starts[:0], torch.zeros(0, dtype=DTYPE)
    if starts.shape[0]:
        X, v = minimize_in_box(goal, box, starts, scale=scale, maxiter=maxiter, ftol=ftol)
    if ls_starts is not None:
        X_ls = lo + width * ls_starts
        with torch.no_grad():
            v_ls = goal(X_ls)
        X, v = torch.cat([X, X_ls]), torch.cat([v.to(v_ls), v_ls])
    return X, v


class MergedReadings:
    r"""Readings merged by setting: each distinct setting once, with the sum and count of the
    observables read there (the fit's rows are their means, weighted by the counts: the same
    least squares as the unmerged readings, fewer model rows)."""

    def __init__(self) -> None:
        self.x: list[torch.Tensor] = []
        self.sums: list[torch.Tensor] = []
        self.counts: list[int] = []
        self.group: list[int] = []  # the distinct setting of each reading, in order

    def add(self, x: torch.Tensor, o: torch.Tensor) -> None:
        """One reading: observables ``o`` (``m``) at setting ``x`` (``d``)."""
        for k, xu in enumerate(self.x):
            if torch.equal(xu, x):
                self.sums[k] = self.sums[k] + o
                self.counts[k] += 1
                self.group.append(k)
                return
        self.x.append(x)
        self.sums.append(o)
        self.counts.append(1)
        self.group.append(len(self.x) - 1)

    def arrays(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(X, O, n)``: ``K x d`` distinct settings, ``K x m`` mean observables, ``K`` counts."""
        n = torch.tensor(self.counts, dtype=DTYPE)
        return torch.stack(self.x), torch.stack(self.sums) / n.unsqueeze(-1), n

    def scatter(self, O_all: list[torch.Tensor], sd: float) -> float:
        """Sum over the readings ``O_all`` (every reading added, in order) of their squared
        deviations from their setting's mean in units of ``sd`` (the constant the merged fit
        leaves out of the cost)."""
        _, means, _ = self.arrays()
        dev = torch.stack(O_all) - means[torch.tensor(self.group)]
        return float((dev / sd).square().sum())
