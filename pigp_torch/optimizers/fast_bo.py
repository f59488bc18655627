r"""Millisecond Bayesian-optimization steps for a FIXED kernel (the physics-informed GP).

:class:`FastBayesOpt` is the recipe of :class:`~pigp_torch.optimizers.bo.BayesianOptimizer` with
the incremental exact GP (:class:`~pigp_torch.models.incremental_gp.IncrementalPosterior`,
:math:`O(n^2)` per reading, closed-form gradients and Hessians), the core's acquisitions
(:mod:`~pigp_torch.optimizers.bo.acquisition`), the batched Newton search
(:class:`~pigp_torch.optimizers.bo.search.NewtonSearch`) and the trust box: the method of
:class:`~pigp_torch.optimizers.BayesOpt` with the PI-GP model, without rebuilding a BoTorch model
and its caches at every ask.
"""

from __future__ import annotations

import torch

from pigp_torch._utils import as_knob_tensor, check_bounds
from pigp_torch.models._prior_mean import prior_mean_value
from pigp_torch.models.incremental_gp import (
    MIN_NOISE_VARIANCE,
    MIN_VARIANCE,
    IncrementalGP,
    IncrementalPosterior,
)
from pigp_torch.optimizers.bo import BayesianOptimizer, BOParts, NewtonSearch, TrustRegion
from pigp_torch.optimizers.bo.acquisition import ACQUISITIONS, _log_h, analytic
from pigp_torch.optimizers.bo.defaults import BO_DEFAULTS, NEWTON_SEARCH_DEFAULTS
from pigp_torch.optimizers.bo.search import (
    DAMPING_TRIALS,
    NEWTON_MAX_DIM,
    SOLVER_DEFAULTS,
    maximize_in_unit_box,
)

#: Acquisitions of :class:`FastBayesOpt` (the names of :class:`BayesOpt`).
FAST_ACQUISITIONS = ACQUISITIONS

__all__ = [
    "DAMPING_TRIALS",
    "FAST_ACQUISITIONS",
    "MIN_NOISE_VARIANCE",
    "MIN_VARIANCE",
    "NEWTON_MAX_DIM",
    "SOLVER_DEFAULTS",
    "FastBayesOpt",
    "IncrementalGP",
    "_log_h",
    "maximize_in_unit_box",
]


class FastBayesOpt(BayesianOptimizer):
    r"""Bayesian optimization with a fixed full-precision RBF kernel in milliseconds per step.

    Same method as :class:`~pigp_torch.optimizers.BayesOpt` with the model
    :func:`~pigp_torch.models.physics_informed_gp` (kernel ``"rbf"``): the acquisition is
    maximized inside the trust box

    .. math:: \max\!\big(\ell,\; c - s\,\tfrac{h - \ell}{2}\big) \le x \le
              \min\!\big(h,\; c + s\,\tfrac{h - \ell}{2}\big)

    around the center :math:`c` (``"best_observed"``: the best noisy reading, first one on ties;
    ``"best_mean"``: the told point of highest posterior mean), clamped into the bounds; the
    proposal never leaves the bounds or the box. Acquisitions (internal, maximized sign):
    ``"ucb"`` :math:`\mu + \sqrt\beta\,\sigma`, ``"ei"`` :math:`\sigma h(z)`,
    ``"logei"`` :math:`\log(\sigma h(z))` with :math:`z = (\mu - y^*)/\sigma`,
    :math:`h(z) = \varphi(z) + z\Phi(z)` and :math:`y^*` the best observed value -- BoTorch's
    ``UpperConfidenceBound``, ``ExpectedImprovement`` and ``LogExpectedImprovement``.

    **Model.** The posterior is :class:`IncrementalGP` (exact, updated in :math:`O(n^2)` per
    :meth:`tell`). With ``maximize=False`` the GP sees :math:`-y` and the prior mean is negated
    with it: ``mean`` is always given in the objective's own units.

    **Acquisition search.** In the unit cube of the trust box: ``raw_samples`` uniform random
    points are scored in one batch; the ``num_restarts`` best of them, the box center and the last
    ``n_previous`` proposals (clipped into the box; duplicates dropped) are the starts of the
    batched projected Newton method
    :func:`~pigp_torch.optimizers.bo.search.maximize_in_unit_box` (closed-form Hessians) or of one
    stacked L-BFGS-B problem (closed-form gradients), see ``method``; the best point among the
    optimized starts and the raw samples is proposed.

    **Determinism.** The random points come from ``numpy.random.default_rng(seed + n_told)``; no
    global RNG is used.

    After each ask, ``last_info`` holds ``acq_value``, ``center``, ``trust_lower``,
    ``trust_upper``, ``fit_time_s`` (time of the last :meth:`tell`'s model update),
    ``acq_time_s``, ``n_train``, ``n_starts``, ``n_evals`` (batched acquisition evaluations),
    ``iterations`` (accepted steps of the slowest start, or L-BFGS-B iterations) and ``solver``.

    Args:
        bounds: ``2 x d`` knob bounds.
        precision: ``d x d`` kernel precision :math:`P` (1 / knob²).
        amplitude: kernel variance :math:`\sigma_f^2`.
        noise: measurement noise standard deviation :math:`\sigma_n` (variance floored at
            :data:`MIN_NOISE_VARIANCE`, as GPyTorch does).
        mean: prior mean in objective units: a float or a differentiable callable
            ``(X: N x d) -> N`` (e.g. a gpytorch ``Mean``); change it later with
            :meth:`set_mean`.
        acquisition: ``"ucb"``, ``"ei"``, ``"logei"`` or an acquisition part of the core
            (:mod:`~pigp_torch.optimizers.bo.acquisition`, e.g. ``UCB(2.0)``; any object with
            ``bind(posterior, best_f, step)``).
        beta: UCB trade-off :math:`\beta \ge 0` (``4``: the authors' :math:`\mu + 2\sigma`).
        step_limit: trust-box half-width as a fraction of each knob's half-range, or ``None``.
        trust_center: ``"best_observed"`` or ``"best_mean"``.
        maximize: maximize (default) or minimize the objective.
        num_restarts: best random points kept as starts (>= 0).
        raw_samples: random points scored to pick them (>= ``num_restarts``).
        seed: base seed of the per-ask random points.
        method: ``"newton"`` (:func:`maximize_in_unit_box`), ``"lbfgsb"`` (scipy, stacked
            starts) or ``"auto"`` (Newton unless the prior mean is a callable or there are more
            than :data:`NEWTON_MAX_DIM` knobs).
        options: solver options over :data:`SOLVER_DEFAULTS` of the method.
    """

    name = "fast-bo"

    def __init__(
        self,
        bounds,
        precision,
        *,
        amplitude: float,
        noise: float,
        mean=0.0,
        acquisition=BO_DEFAULTS["acquisition"],
        beta: float = BO_DEFAULTS["beta"],
        step_limit: float | None = BO_DEFAULTS["step_limit"],
        trust_center: str = BO_DEFAULTS["trust_center"],
        maximize: bool = True,
        num_restarts: int = NEWTON_SEARCH_DEFAULTS["num_restarts"],
        raw_samples: int = NEWTON_SEARCH_DEFAULTS["raw_samples"],
        seed: int = 0,
        method: str = "auto",
        options: dict | None = None,
    ) -> None:
        bounds = check_bounds(bounds)
        acq = acquisition if hasattr(acquisition, "bind") else analytic(acquisition, beta)
        region = TrustRegion(bounds, step_limit, trust_center)
        search = NewtonSearch(num_restarts, raw_samples, method, options)
        if method == "newton" and callable(mean):
            raise ValueError("method='newton' needs a constant prior mean; use 'lbfgsb' or 'auto'")
        sign = 1.0 if maximize else -1.0
        gp = IncrementalGP(precision, amplitude, noise, _signed(mean, sign))
        if gp.dim != bounds.shape[1]:
            raise ValueError(f"precision is {gp.dim} x {gp.dim}, bounds have {bounds.shape[1]}")
        parts = BOParts(IncrementalPosterior(gp), acq, search, region)
        super().__init__(bounds, parts, maximize=maximize, seed=seed)
        self.gp = gp
        self.acquisition = getattr(acq, "name", type(acq).__name__)
        self.beta = float(beta)
        self.trust_center = trust_center
        self.num_restarts, self.raw_samples = search.num_restarts, search.raw_samples
        self.method, self.options = method, search.options

    @classmethod
    def from_prior(cls, bounds, prior, *, mean="f_inf", **options) -> FastBayesOpt:
        r"""The PI-GP optimizer of a :class:`~pigp_torch.prior.PhysicsPrior`: precision
        :math:`\Sigma`, amplitude :math:`\sigma_f^2` and noise :math:`\sigma_n` of the prior.

        Args:
            bounds: ``2 x d`` knob bounds.
            prior: the physics prior.
            mean: ``"f_inf"`` (the paper), ``"zero"``, a float or a callable (objective units).
            **options: further :class:`FastBayesOpt` options.
        """
        from pigp_torch.prior import PhysicsPrior

        if not isinstance(prior, PhysicsPrior):
            raise ValueError(f"prior must be a PhysicsPrior, got {type(prior).__name__}")
        if not callable(mean):
            mean = prior_mean_value(prior, mean, what="a float or a callable")
        return cls(bounds, prior.precision, amplitude=prior.amplitude, noise=prior.noise,
                   mean=mean, **options)  # fmt: skip

    @property
    def proposals(self) -> list[torch.Tensor]:
        """The proposals of the asks so far (``d`` each)."""
        return self.parts.search.proposals

    def set_mean(self, mean) -> None:
        """Replace the prior mean (objective units); :math:`O(n^2)`, the factor is kept."""
        if self.method == "newton" and callable(mean):
            raise ValueError("method='newton' needs a constant prior mean; use 'lbfgsb' or 'auto'")
        self.gp.set_mean(_signed(mean, self.sign))

    def posterior(self, X) -> tuple[torch.Tensor, torch.Tensor]:
        r"""Posterior mean and variance of the latent objective at ``X`` (``N x d`` or ``d``), in
        the objective's own sign (the mean is negated back when minimizing)."""
        X, _ = as_knob_tensor(X, self.dim)
        mu, var = self.gp.predict(X.numpy())
        return self.sign * torch.from_numpy(mu), torch.from_numpy(var)

    def acquisition_value(self, X, *, order: int = 0):
        r"""The acquisition (internal, maximized sign) at knob settings ``X`` (``N x d``).

        Returns:
            ``N`` values; with ``order=1`` also the ``N x d`` gradients, with ``order=2`` also
            the ``N x d x d`` Hessians (knob units), as a tuple.
        """
        if order not in (0, 1, 2):
            raise ValueError(f"order must be 0, 1 or 2, got {order}")
        X, _ = as_knob_tensor(X, self.dim)
        if not self.Y:
            raise RuntimeError("no measurements yet: tell() the start point first")
        best = max(self.sign * y for y in self.Y)
        out = self.parts.acquisition.bind(self.parts.posterior, best, self.n_told)(X.numpy(), order)
        if order == 0:
            return torch.from_numpy(out)
        return tuple(torch.from_numpy(o) for o in out)


def _signed(mean, sign: float):
    """The prior mean in the internal (maximized) sign."""
    if sign > 0:
        return mean
    if callable(mean):
        return lambda X: -mean(X)
    return -float(mean)
