r"""Bayesian optimization with the physics form of the objective fitted online (beyond the paper).

The paper's PI-GP fixes a kernel from the model ring and lets a constant-mean GP find the machine's
optimum. Far from the optimum the loss rate is flat (it falls off like :math:`1/\sqrt{1 + q}`), so
a stationary GP learns little per noisy reading. :class:`PhysicsModelBO` instead fits the physics
form itself, :math:`f = f_\infty + (c + \beta(\mathbf x - \boldsymbol\mu)^\top B (\mathbf x -
\boldsymbol\mu))^{-1/2}` with the shape :math:`B` from the same physics prior (the mean over an
error ensemble of model rings when the prior has one, else the model ring's;
:class:`~pigp_torch.models.InverseSqrtPeakModel`), plus a residual GP with the physics-informed
kernel at the fitted optimum, and maximizes the upper confidence bound

.. math:: a(\mathbf x) = \mu(\mathbf x) + \sqrt{\beta_\mathrm{UCB}}\,\sigma(\mathbf x)

in the trust box of half-width ``step_limit`` (knobs normalized to :math:`[-1, 1]`) around the
told point with the highest posterior mean (a single lucky reading cannot move the box). It is
the recipe of :class:`~pigp_torch.optimizers.bo.BayesianOptimizer` with
:class:`~pigp_torch.models.physics_posterior.PhysicsFormPosterior` (the form, the residual GP and
the prior check), :class:`~pigp_torch.optimizers.bo.UCB` alternating with
:class:`~pigp_torch.optimizers.bo.CentreInformation` every ``info_every``-th ask (the UCB alone
reads near the fitted peak, where the form is flat and says little about where the centre lies),
multi-start L-BFGS-B (:class:`~pigp_torch.optimizers.bo.MultiStartLBFGSB`: Sobol points of the
box, the box centre and the fitted centre projected into it) and the trust box with an optional
travel limit (:class:`~pigp_torch.optimizers.bo.TrustRegion`).

A machine that drifts is followed by itself (no option): the posterior's learned memory
(:class:`~pigp_torch.models.forgetting.Forgetting`) inflates old readings' noise variance by
:math:`e^{\mathrm{age}/\tau}` with :math:`\tau` chosen by the predictive likelihood of recent
readings (:math:`\infty`, every reading for good, on a static machine: its runs are unchanged),
tracks a height that changes (a decaying current) by a log-height slope chosen with
:math:`\tau`, so the centre keeps the longer memory its own motion allows, and restarts the
memory at a step found by a CUSUM of the innovations. While it follows a drift
the fitted centre and height move with the machine, the trust box sits at the told point of
highest *current* posterior mean, and every ask is the UCB with :math:`\beta = 1`, closer to
the fitted optimum than the static machine's :math:`\beta = 4` (``track_schedule``,
``track_beta``). :meth:`PhysicsModelBO.recommend` is the fitted optimum now and
:meth:`PhysicsModelBO.tracked` the fitted peak, the centre's travel and the memory.
"""

from __future__ import annotations

import math

import torch

from pigp_torch._utils import check_bounds
from pigp_torch.models.inverse_sqrt import InverseSqrtPeakModel
from pigp_torch.models.physics_posterior import (
    BROADER_SHAPE,
    RELAXED_STAGES,
    PhysicsFormPosterior,
    describe_stage,
    relaxed_stages,
)
from pigp_torch.optimizers.bo import (
    UCB,
    Alternating,
    BayesianOptimizer,
    BOParts,
    CentreInformation,
    CorrelatedCentreInformation,
    ExpectedCentreInformation,
    MultiStartLBFGSB,
    Schedule,
    TrustRegion,
    WhileDrifting,
)
from pigp_torch.optimizers.bo.defaults import PHYSICS_DEFAULTS
from pigp_torch.prior import PhysicsPrior

__all__ = [
    "BROADER_SHAPE",
    "RELAXED_STAGES",
    "PhysicsModelBO",
    "describe_stage",
    "relaxed_stages",
]


class PhysicsModelBO(BayesianOptimizer):
    r"""UCB on the online-fitted physics form (see the module docstring). Maximizes only.

    Args:
        bounds: ``2 x d`` knob bounds.
        prior: the model ring's physics prior (shape :math:`B`, :math:`f_\infty`, noise).
        beta: UCB trade-off (BoTorch convention; 4 is :math:`\mu + 2\sigma`).
        step_limit: trust-box half-width as a fraction of each knob's half-range (``None``: the
            whole box).
        n_starts: Sobol starts of the acquisition search (plus two informed starts).
        info_every: if ``k > 0``, every ``k``-th ask (not an exploit ask) maximizes
            :meth:`centre_information` instead of the UCB: the reading that most shrinks the
            fitted centre's uncertainty in the metric of :math:`B`. Near the peak the form is
            flat, so readings there say little about where the centre is; the most informative
            ones lie at about :math:`\sqrt{c/2}` from it in that metric. Default 3 (every
            third ask; 0 turns it off).
        schedule: the acquisition of every ask as a :class:`~pigp_torch.optimizers.bo.Schedule`
            of the letters ``u`` (the UCB with ``beta``), ``m`` (the posterior mean, the UCB
            with :math:`\beta = 0`: a visit of the fitted optimum), ``w`` (the UCB with
            ``track_beta``), ``i`` (the centre
            information), ``c`` (the same with the readings' errors correlated by the
            residual GP, :class:`~pigp_torch.optimizers.bo.CorrelatedCentreInformation`) and
            ``e`` (that, averaged over the Laplace posterior of the form's parameters,
            :class:`~pigp_torch.optimizers.bo.ExpectedCentreInformation`); overrides
            ``info_every`` (``None``, default: ``info_every``'s
            alternation of ``u`` and ``i``). ``"uue"`` is the best early-phase schedule
            screened (docs/results.md), an option, not the default.
        track_schedule: the schedule (letters as ``schedule``) while the learned memory
            follows a drift (a finite memory, a changing height or a detected step:
            ``forgetting`` below); default ``"w"``, the UCB with ``track_beta`` at every
            ask: a drifting machine is tracked by reading near where the current fit puts
            the optimum, and the centre-information asks, which read away from the peak,
            cost gain there (as do the wider UCB asks of ``beta``).
        track_beta: the UCB trade-off of the letter ``w`` (default 1: :math:`\mu + \sigma`).
        seed: base seed (the Sobol starts of step ``n`` use ``seed + n``).
        travel_limit: a hard step limit of the proposals (a fraction of each knob's half-range:
            one value or ``d``), or ``None`` (default: none). The search box is the trust box
            intersected with the box of this half-width around the last told point; where the
            two do not overlap (the best point lies far from the last one) the travel box alone
            is used, so a proposal never moves a knob farther than the limit.
        center_prior: prior on the fitted centre (where the machine's optimum lies):
            ``"ensemble"``: from the error ensemble of the model rings,
            :attr:`prior.center_cov <pigp_torch.prior.PhysicsPrior>`; ``"box"``: isotropic,
            ``center_std`` half-ranges around the box centre; ``"auto"`` (default): the
            ensemble when the prior has one.
        shape_prior: shape :math:`B` of the physics form: ``"ensemble"``: the mean over the
            error ensemble, :attr:`prior.peak_shape <pigp_torch.prior.PhysicsPrior>`;
            ``"model"``: the model ring's own, :math:`2 c_m \Sigma`; ``"auto"`` (default): the
            ensemble's when the prior has one.
        prior_check: test whether the physics prior still explains the readings, and move,
            for good, to other models (another scale of the shape, wider priors) when it does
            not (default on). The models are the given one (stage 0) and the stages of
            ``relax``, each a set of options over the given ones. From :math:`n \ge p + 5`
            readings on (:math:`p` parameters of the current model; the evidence test from
            ``evidence_from`` if given) two tests run:

            * the misfit of the fitted form at every ask (residual GP excluded),
              :math:`z = (\chi^2 - \nu)/\sqrt{2\nu}`, :math:`\chi^2 = \sum_i (y_i -
              f(\mathbf x_i;\hat\theta))^2/\sigma_n^2`, :math:`\nu = n - p`, about
              :math:`\mathcal N(0, 1)` when the form is right; :math:`z >` ``check_z`` moves
              to the last stage;
            * every ``check_every``-th ask the later stages are fitted too and compared with
              the current one by their Laplace evidence
              (:meth:`~pigp_torch.models.InverseSqrtPeakModel.log_evidence`); the best of them
              takes over when it leads by more than ``evidence_margin`` (a wrong scale of the
              shape leaves the residuals small but needs a :math:`\log\beta` far out in its
              prior).

            Each move (the new model warm-started from the current fit) writes a notice
            (``kind = "prior_rejected"``, with ``stage``, ``z``, ``chi2``, ``nu``, ``n``,
            ``log_evidence_ratio``) to :attr:`notices` for the run log and the progress line.
        check_z: misfit threshold (default 4).
        evidence_margin: log-evidence lead that moves to a later stage (default 1.5 nats, odds
            of :math:`e^{1.5} \approx 4.5` to 1: the later stages nest the given model, so a
            lead needs readings that the given one explains badly).
        check_every: period of the evidence comparison in asks (default 3; it costs one more
            fit per later stage).
        evidence_from: readings from which the evidence comparison runs (default 10; ``None``:
            :math:`p + 5`, as the misfit test; the comparison needs no residual degrees of
            freedom, so it may start before the misfit test).
        relax: the stages after the given model (default :data:`RELAXED_STAGES`: first the
            given shape 3x broader, ``shape_factor = 1/3``, with the given priors; then the
            scale and the background free, ``log_beta_std = 3``, ``f_inf_std = 0.1``; then also
            the shape's eigen-scales, ``shape_std = 1``, and a centre prior 4x wider in
            variance). Each stage is a dict of model options over the given ones, plus two
            relative ones: ``shape_factor`` multiplies the given shape :math:`B` (the warm start
            keeps :math:`\beta B`), ``center_cov_scale_factor`` the given
            ``center_cov_scale``.
        **posterior_options: ``center_prior``, ``shape_prior``, the prior check's options above
            (:class:`~pigp_torch.models.physics_posterior.PhysicsFormPosterior`) and
            :class:`~pigp_torch.models.InverseSqrtPeakModel` options
            (``center_std``, ``center_cov_scale``, ``center_floor_std``, ``log_c_std``,
            ``log_beta_std``, ``residual_std``, ``f_inf_std``, ``shape_std``, ``noise``, and
            ``gls``: the form fitted with the residual GP's covariance of the readings; off by
            default), and ``forgetting``: the learned memory of a drifting machine
            (:class:`~pigp_torch.models.forgetting.Forgetting`: old readings' noise variance
            grows as :math:`e^{\mathrm{age}/\tau}`, :math:`\tau` chosen by the predictive
            likelihood of recent readings, :math:`\infty` on a static machine, where every
            fit equals the one without it; a changing height is followed by a log-height
            slope per reading chosen with :math:`\tau`, 0 on a static machine; a step is
            detected by a CUSUM of the innovations and the memory restarts; on by default,
            ``False`` turns it off, a dict sets its options).

    After each ask, ``last_info`` holds ``center`` (trust-box centre), ``fitted_center``,
    ``fitted_peak``, ``acq_value``, ``inform``, ``misfit_z``, ``log_evidence_ratio``,
    ``relaxed``, ``memory_readings`` (the learned :math:`\tau`), ``fit_time_s``,
    ``acq_time_s``.
    """

    name = "pigp-physics"
    #: Units of :meth:`tracked` (the loss rate and the skew-quadrupole currents of SPEAR3).
    objective_unit, knob_unit = "mA/min", "A"

    def __init__(
        self,
        bounds,
        prior: PhysicsPrior,
        *,
        beta: float = PHYSICS_DEFAULTS["beta"],
        step_limit: float | None = PHYSICS_DEFAULTS["step_limit"],
        n_starts: int = PHYSICS_DEFAULTS["n_starts"],
        info_every: int = PHYSICS_DEFAULTS["info_every"],
        schedule: str | None = None,
        track_schedule: str = PHYSICS_DEFAULTS["track_schedule"],
        track_beta: float = PHYSICS_DEFAULTS["track_beta"],
        seed: int = 0,
        travel_limit=None,
        maximize: bool = True,
        **posterior_options,
    ) -> None:
        if not maximize:
            raise ValueError("PhysicsModelBO models a peak: it maximizes only")
        bounds = check_bounds(bounds)
        ucb = UCB(beta)
        region = TrustRegion(bounds, step_limit, "best_mean", travel_limit)
        search = MultiStartLBFGSB(n_starts, maxiter=200)
        posterior = PhysicsFormPosterior(prior, bounds, **posterior_options)
        letters = {"u": ucb, "m": UCB(0.0), "i": CentreInformation()}
        letters.update(c=CorrelatedCentreInformation(), e=ExpectedCentreInformation())
        letters["w"] = UCB(track_beta)
        if schedule is None:
            acquisition = Alternating(ucb, CentreInformation(), info_every)
        else:
            acquisition = Schedule(letters, schedule)
        acquisition = WhileDrifting(acquisition, Schedule(letters, track_schedule))
        self.schedule = schedule
        super().__init__(bounds, BOParts(posterior, acquisition, search, region), seed=seed)
        self.prior = prior
        self.beta = ucb.beta
        self.n_starts, self.info_every = search.n_starts, int(info_every)
        self.travel_limit = region.travel_limit
        self._centre_ref: torch.Tensor | None = None  # the first fit's centre (tracked())

    # -- the physics posterior's state, under the names of the method ---------------------------
    @property
    def model(self) -> InverseSqrtPeakModel:
        """The current physics-form model (the prior check may replace it)."""
        return self.parts.posterior.model

    def __getattr__(self, name: str):
        # prior-check state and options live on the posterior (stage, misfit_z, check_z, ...)
        if name in _POSTERIOR_ATTRIBUTES:
            return getattr(self.parts.posterior, name)
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")

    def search_box(self, center: torch.Tensor) -> torch.Tensor:
        """The ``2 x d`` box the acquisition is maximized in: :meth:`trust_box` of ``center``,
        within ``travel_limit`` of the last told point when a travel limit is set."""
        return self.parts.region.box(center, self.X[-1])

    def acquisition(self, X: torch.Tensor, beta: float | None = None) -> torch.Tensor:
        r""":math:`\mu + \sqrt\beta\,\sigma` at ``n x d`` settings (after a fit)."""
        mu, sd = self.model.predict(X)
        beta = self.beta if beta is None else beta
        return mu + math.sqrt(beta) * sd if beta > 0 else mu

    def centre_information(self, X: torch.Tensor) -> torch.Tensor:
        r"""Reduction of :math:`\mathrm{tr}(B\,C_\mu)` by one more reading at each of ``n x d``
        settings (after a fit), :math:`C_\mu` the Laplace covariance of the fitted centre:
        with :math:`C` the covariance of :math:`\theta`, :math:`\mathbf j = \partial f /
        \partial\theta` and :math:`\mathbf v = C\mathbf j`, the trace falls by
        :math:`\mathbf v_\mu^\top B\, \mathbf v_\mu / (\sigma_n^2 + \mathbf j^\top C
        \mathbf j)` (Sherman-Morrison). Differentiable (torch); the ask maximizes the same
        quantity with its closed-form gradient."""
        model = self.model
        J = model.jacobian(X)
        V = J @ model.cov
        Vmu = V[..., : model.dim]
        return ((Vmu @ model.shape()) * Vmu).sum(-1) / (model.noise**2 + (V * J).sum(-1))

    def ask(self) -> torch.Tensor:
        """Fit the physics form to the remembered readings, maximize the UCB (or the centre
        information) in the trust box; returns ``d``."""
        x = super().ask()
        self.last_info["inform"] = isinstance(self.parts.acquisition.last, CentreInformation)
        if self._centre_ref is None:
            self._centre_ref = self.model.center()
        return x

    def recommend(self) -> torch.Tensor:
        r"""The current estimate of the best setting (``d``): the fitted form's optimum in the
        knob box (:meth:`~pigp_torch.models.InverseSqrtPeakModel.box_optimum`, the fitted
        centre when it lies inside), which follows a drifting machine through the learned
        memory; the best reading before the first fit."""
        if self.model.theta is None:
            return self.best()[0]
        return self.model.box_optimum()[0]

    def tracked(self) -> dict[str, tuple[float, str]]:
        r"""The tracked unknowns now, name -> ``(value, unit)``: ``peak`` the fitted peak
        :math:`f_\infty + \hat c^{-1/2}` (:attr:`objective_unit`), ``centre_moved`` the
        Euclidean distance of the fitted centre from the first fit's (:attr:`knob_unit`) and
        ``remembered`` the readings the fit remembers, :math:`\sum_i w_i` (readings); ``{}``
        before the first fit."""
        if self.model.theta is None or self._centre_ref is None:
            return {}
        moved = float(torch.linalg.vector_norm(self.model.center() - self._centre_ref))
        w = self.model.weights
        kept = float(self.model._X.shape[0] if w is None else w.sum())
        return {
            "peak": (self.model.peak(), self.objective_unit),
            "centre_moved": (moved, self.knob_unit),
            "remembered": (kept, "readings"),
        }


#: Attributes of :class:`PhysicsModelBO` read from its posterior.
_POSTERIOR_ATTRIBUTES = frozenset(
    ("stage", "misfit_z", "log_evidence_ratio", "relaxed", "relax", "prior_check", "check_z",
     "evidence_margin", "check_every", "evidence_from", "center_prior", "shape_prior",
     "model_options", "misfit", "_stage_model", "_alternatives")
)  # fmt: skip
