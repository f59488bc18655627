r"""A GP on what a fitted model does not explain: the residual of each observable.

A fitted physics model :math:`M(x, \hat\theta)` that lacks some of the machine's physics (a
rolled quadrupole, a corrector's calibration, a screen's resolution) fits the readings in the
least-squares sense and still misses them near the present setting by a structured amount; the
optimum of the fitted model is then a fixed distance from the machine's. The residuals of the
last readings,

.. math:: r_i = o_i - M(x_i, \hat\theta) \in \mathbb R^m,

are given to one GP per observable :math:`j` (zero mean, squared-exponential kernel on the knobs
scaled by their ranges, :math:`k(x, x') = a_j^2 \exp(-\|(x - x') / (\ell\, \Delta x)\|^2 / 2)`,
noise :math:`s_j`), and the model asked is :math:`M(x, \hat\theta) + \hat r(x)` with
:math:`\hat r` the posterior mean: at the present setting the corrected model reads what the
machine read, so its optimum moves by the model's gradient from there and a run converges to
the machine's optimum when the model's slopes are roughly right (the residual's fixed point is a
root of the goal's residuals on the machine, not on the model).

The hyperparameters come from a grid, by each observable's marginal likelihood: the length
:math:`\ell` (fractions of each knob's range, shared by the observables: :data:`LENGTHS`), the
noise :math:`s_j = f s` (:data:`NOISE_FACTORS` times the stated noise :math:`s`: a screen's
scatter is rarely only its stated noise) and the amplitude :math:`a_j` (:data:`AMPLITUDE_FACTORS`
times the rms residual). The GP is used only when it explains the residuals better than noise
alone, :math:`\sum_j \log p_{GP} - \sum_j \max_f \log N(r_j; 0, (f s)^2 I) \ge`
:data:`MIN_GAIN_NATS`: a machine its model explains keeps the model's asks exactly.

Written here because the GP is tiny (at most :data:`WINDOW` points, four outputs, a fixed grid
of a few hundred hyperparameter sets solved in one batched Cholesky) and is evaluated inside
the ask's batched Levenberg–Marquardt search, where a GPyTorch model's overhead per call would
dominate.
"""

from __future__ import annotations

import math

import torch

from pigp_torch._utils import DTYPE

__all__ = [
    "LENGTHS",
    "MIN_GAIN_NATS",
    "WINDOW",
    "ResidualGP",
    "fit_residual_gp",
    "tracker_residual_gp",
]

#: The last readings given to the GP.
WINDOW: int = 20
#: Length scales (fraction of each knob's range), noise factors (of the stated noise) and
#: amplitude factors (of each observable's rms residual) of the grid.
LENGTHS: tuple[float, ...] = (0.01, 0.03, 0.1, 0.3, 1.0)
NOISE_FACTORS: tuple[float, ...] = (1.0, 2.0, 4.0, 8.0, 16.0, 32.0)
AMPLITUDE_FACTORS: tuple[float, ...] = (0.25, 0.5, 1.0, 2.0, 4.0)
#: The log-likelihood (nats, summed over the observables) by which the GP must beat noise alone.
MIN_GAIN_NATS: float = 6.0


class ResidualGP:
    r"""The posterior mean :math:`\hat r(x)` of the residual GPs (module docstring).

    Args:
        Z: ``n x d`` settings of the readings, scaled by the knobs' ranges.
        alpha: ``n x m`` weights :math:`(K_j + s_j^2 I)^{-1} r_j`, one column per observable.
        length: ``m`` length scales (scaled units); amplitude: ``m`` amplitudes :math:`a_j`
            (observable units); noise: ``m`` noise sd :math:`s_j` (observable units).
        scale: ``d`` knob ranges; gain_nats: the log-likelihood gain over noise alone.
    """

    def __init__(self, Z, alpha, length, amplitude, noise, scale, gain_nats: float) -> None:
        self.Z, self.alpha = Z, alpha
        self.length, self.amplitude, self.noise = length, amplitude, noise
        self.scale = scale
        self.gain_nats = float(gain_nats)

    def __call__(self, X: torch.Tensor) -> torch.Tensor:
        """The posterior mean at ``... x d`` settings (knob units): ``... x m`` (observable
        units); differentiable in ``X``."""
        z = X[..., None, :] / self.scale  # ... x 1 x d
        d2 = (z - self.Z).square().sum(-1, keepdim=True)  # ... x n x 1
        k = self.amplitude.square() * torch.exp(-0.5 * d2 / self.length.square())  # ... x n x m
        return (k * self.alpha).sum(-2)


def _log_likelihoods(d2, R, length, amp, noise):
    """Log marginal likelihoods of every grid point: ``L x A x F x m`` (nats)."""
    n = R.shape[0]
    K = torch.exp(-0.5 * d2 / length.square()[:, None, None, None, None, None])  # L,1,1,1,n,n
    K = amp.square()[None, :, None, :, None, None] * K  # L,A,1,m,n,n (amp: A x m)
    K = K + noise.square()[None, None, :, :, None, None] * torch.eye(n, dtype=R.dtype)
    Lc, info = torch.linalg.cholesky_ex(K)
    r = R.T[None, None, None, :, :, None].expand(*K.shape[:-1], 1)
    w = torch.cholesky_solve(r, Lc)
    quad = (r * w).sum((-2, -1))
    logdet = 2 * torch.log(torch.diagonal(Lc, dim1=-2, dim2=-1)).sum(-1)
    ll = -0.5 * (quad + logdet + n * math.log(2 * math.pi))
    return torch.where(info == 0, ll, torch.full_like(ll, -torch.inf)), Lc, r


def fit_residual_gp(X, R, bounds, noise_sd: float) -> ResidualGP | None:
    r"""The residual GP of ``n x m`` residuals ``R`` at ``n x d`` settings ``X`` (module
    docstring), or ``None`` when noise alone explains them as well (within
    :data:`MIN_GAIN_NATS`) or there are fewer than 3 readings.

    Args:
        X: ``n x d`` settings (knob units); R: ``n x m`` residuals (observable units).
        bounds: ``2 x d`` knob bounds (their ranges scale the settings).
        noise_sd: the stated noise :math:`s` of each observable (observable units, > 0).
    """
    X = torch.as_tensor(X, dtype=DTYPE)
    R = torch.as_tensor(R, dtype=DTYPE)
    n, m = R.shape
    if n < 3 or not bool(torch.isfinite(R).all()):
        return None
    lo, hi = torch.as_tensor(bounds, dtype=DTYPE)
    scale = (hi - lo).clamp_min(1e-300)
    Z = X / scale
    d2 = (Z[:, None, :] - Z[None, :, :]).square().sum(-1)
    length = torch.tensor(LENGTHS, dtype=DTYPE)
    noise_f = torch.tensor(NOISE_FACTORS, dtype=DTYPE) * float(noise_sd)
    rms = R.square().mean(0).sqrt().clamp_min(1e-3 * float(noise_sd))  # m
    amp = torch.tensor(AMPLITUDE_FACTORS, dtype=DTYPE)[:, None] * rms  # A x m
    noise = noise_f[:, None].expand(-1, m)  # F x m
    ll, Lc, r = _log_likelihoods(d2, R, length, amp, noise)  # L x A x F x m
    # noise alone, per observable at its best noise factor
    null = -0.5 * (R.square().sum(0) / noise.square() + 2 * n * torch.log(noise)
                   + n * math.log(2 * math.pi))  # fmt: skip
    best_null = null.max(0).values  # m
    # the length is shared by the observables; amplitude and noise per observable
    per_length = ll.flatten(1, 2).max(1)  # values L x m
    total = per_length.values.sum(-1)  # L
    i = int(total.argmax())
    gain = float(total[i] - best_null.sum())
    if not gain >= MIN_GAIN_NATS:
        return None
    idx = per_length.indices[i]  # m: flat (A, F) index per observable
    a_i, f_i = idx // len(NOISE_FACTORS), idx % len(NOISE_FACTORS)
    cols = torch.arange(m)
    L = Lc[i, a_i, f_i, cols]  # m x n x n
    alpha = torch.cholesky_solve(r[i, a_i, f_i, cols], L)[..., 0].T  # n x m
    return ResidualGP(
        Z,
        alpha,
        torch.full((m,), float(length[i]), dtype=DTYPE),
        amp[a_i, cols],
        noise[f_i, cols],
        scale,
        gain,
    )


def tracker_residual_gp(opt) -> ResidualGP | None:
    """The residual GP of the last readings of a :class:`~pigp_torch.optimizers.tracking.
    TrackingModelOptimizer` ``opt`` (:func:`fit_residual_gp`; ``None`` also during its noise
    probe, after a hand-over and with fewer than 3 readings since its last step alarm): the
    residuals of the model its ask optimizes (while tracking, the tracked model with its offset
    and play) at the acting fields, the last :data:`WINDOW` readings at most."""
    probing = bool(opt._probe and opt._probe[1] > 0)
    if opt.fallback is not None or probing or not opt.O:
        return None
    k = min(WINDOW, opt.n_told - (opt.steps[-1] if opt.steps else 0))
    if k < 3:
        return None
    O, X = torch.stack(opt.O[-k:]), torch.stack(opt.X[-k:])
    with torch.no_grad():
        if opt.tracking:
            pred = opt.filter.model(opt._rows(k), opt._filter_theta())
            if opt._used_play is not None:
                X = X + opt._used_play[0][-k:]
        else:
            pred = opt.model(X, opt.theta.detach())
    return fit_residual_gp(X, O - pred, opt.bounds, opt.obs_sd)
