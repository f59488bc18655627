r"""Bayesian optimization with the physics form of the objective fitted online (beyond the paper).

The paper's PI-GP fixes a kernel from the model ring and lets a constant-mean GP find the machine's
optimum. On our benchmark that stalls at 45-70 % of the achievable gain: far from the optimum the
loss rate is flat (it falls off like :math:`1/\sqrt{1 + q}`), so a stationary GP learns little per
noisy reading. :class:`PhysicsModelBO` instead fits the physics form itself,
:math:`f = f_\infty + (c + \beta(\mathbf x - \boldsymbol\mu)^\top B (\mathbf x -
\boldsymbol\mu))^{-1/2}` with the shape :math:`B` from the same physics prior (the mean over an
error ensemble of model rings when the prior has one, else the model ring's;
:class:`~pigp_torch.models.InverseSqrtPeakModel`), plus a residual GP with the physics-informed
kernel at the fitted optimum, and maximizes the upper confidence bound

.. math:: a(\mathbf x) = \mu(\mathbf x) + \sqrt{\beta_\mathrm{UCB}}\,\sigma(\mathbf x)

in the trust box of half-width ``step_limit`` (knobs normalized to :math:`[-1, 1]`) around the
told point with the highest posterior mean (a single lucky reading cannot move the box). The UCB is
maximized by multi-start L-BFGS-B (:func:`pigp_torch._multistart.find_optimum`) from Sobol points
of the box, the box centre and the fitted centre :math:`\hat{\boldsymbol\mu}` projected into it.
Every third ask (``info_every``) maximizes instead the information about the fitted centre
(:meth:`PhysicsModelBO.centre_information`): the UCB alone reads near the fitted peak, where the
form is flat and says little about where the centre lies.
"""

from __future__ import annotations

import math
import time

import torch

from pigp_torch._multistart import find_optimum
from pigp_torch._utils import DTYPE
from pigp_torch.models.inverse_sqrt import InverseSqrtPeakModel
from pigp_torch.optimizers.base import AskTellOptimizer, check_ucb_options, trust_box
from pigp_torch.prior import PhysicsPrior


class PhysicsModelBO(AskTellOptimizer):
    r"""UCB on the online-fitted physics form (see the module docstring). Maximizes only.

    Args:
        bounds: ``2 x d`` knob bounds.
        prior: the model ring's physics prior (shape :math:`B`, :math:`f_\infty`, noise).
        beta: UCB trade-off (BoTorch convention; 4 is :math:`\mu + 2\sigma`).
        step_limit: trust-box half-width as a fraction of each knob's half-range (``None``: the
            whole box).
        n_starts: Sobol starts of the acquisition search (plus two informed starts).
        exploit_every: if ``k > 0``, every ``k``-th ask maximizes the posterior mean alone
            (:math:`\beta = 0`) instead of the UCB: the benchmark scores the best *true* value
            visited, and near the peak the noise (0.04) is as large as the last few per cent of
            the gain, so a model-averaged best guess is worth a measurement.
        info_every: if ``k > 0``, every ``k``-th ask (not an exploit ask) maximizes
            :meth:`centre_information` instead of the UCB: the reading that most shrinks the
            fitted centre's uncertainty in the metric of :math:`B`. Near the peak the form is
            flat, so readings there say little about where the centre is; the most informative
            ones lie at about :math:`\sqrt{c/2}` from it in that metric. Default 3 (every
            third ask; 0 turns it off).
        adapt_box: shrink and grow the trust box like TuRBO (Eriksson et al. 2019), counting
            asks: a *success* when the best posterior mean over the told points rose by more
            than ``success_tol`` since the previous ask, else a *failure*;
            ``success_streak`` successes in a row double the half-width (up to ``step_limit``),
            ``failure_streak`` failures in a row halve it (down to ``min_step_limit``). A box
            that keeps missing (the model's peak moved, the reading did not follow) thus turns
            the method into a local search around the best point. Off by default.
        min_step_limit, success_streak, failure_streak: the adaptation's floor and streaks.
        success_tol: improvement of the best posterior mean that counts as a success
            (default: a quarter of the model's noise).
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
            of about 4.5 to 1: the later stages nest the given model, so a lead needs readings
            that the given one explains badly; a wrong scale of the shape leads by only 1-2
            nats for tens of readings).
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
        **model_options: :class:`~pigp_torch.models.InverseSqrtPeakModel` options
            (``center_std``, ``center_cov_scale``, ``center_floor_std``, ``log_c_std``,
            ``log_beta_std``, ``residual_std``, ``f_inf_std``, ``shape_std``, ``noise``).

    After each ask, ``last_info`` holds ``center`` (trust-box centre), ``fitted_center``,
    ``fitted_peak``, ``acq_value``, ``misfit_z``, ``log_evidence_ratio``, ``relaxed``,
    ``fit_time_s``, ``acq_time_s``.
    """

    name = "pigp-physics"

    def __init__(
        self,
        bounds,
        prior: PhysicsPrior,
        *,
        beta: float = 4.0,
        step_limit: float | None = 0.6,
        n_starts: int = 8,
        exploit_every: int = 0,
        info_every: int = 3,
        adapt_box: bool = False,
        min_step_limit: float = 0.075,
        success_streak: int = 3,
        failure_streak: int = 4,
        success_tol: float | None = None,
        seed: int = 0,
        center_prior: str = "auto",
        shape_prior: str = "auto",
        travel_limit=None,
        prior_check: bool = True,
        check_z: float = 4.0,
        evidence_margin: float = 1.5,
        check_every: int = 3,
        evidence_from: int | None = 10,
        relax=None,
        maximize: bool = True,
        **model_options,
    ) -> None:
        super().__init__(bounds, maximize=maximize)
        if not self.maximize:
            raise ValueError("PhysicsModelBO models a peak: it maximizes only")
        check_ucb_options(beta, step_limit)
        if int(n_starts) < 0:
            raise ValueError(f"n_starts must be >= 0, got {n_starts}")
        self.center_prior = _choose(center_prior, "center_prior", "box", prior.center_cov,
                                    "center_cov", model_options)  # fmt: skip
        self.shape_prior = _choose(shape_prior, "shape_prior", "model", prior.peak_shape,
                                   "shape", model_options)  # fmt: skip
        self.model = InverseSqrtPeakModel(prior, self.bounds, **model_options)
        self._given_shape = self.model.B  # the given model's shape B (stages may rescale it)
        self.prior = prior
        self.model_options = dict(model_options)
        self.prior_check = bool(prior_check)
        if not (math.isfinite(float(check_z)) and float(check_z) > 0):
            raise ValueError(f"check_z must be positive and finite, got {check_z}")
        self.check_z = float(check_z)
        if not (math.isfinite(float(evidence_margin)) and float(evidence_margin) >= 0):
            raise ValueError(f"evidence_margin must be >= 0 and finite, got {evidence_margin}")
        self.evidence_margin = float(evidence_margin)
        if int(check_every) < 1:
            raise ValueError(f"check_every must be >= 1, got {check_every}")
        self.check_every = int(check_every)
        if evidence_from is not None and int(evidence_from) < 2:
            raise ValueError(f"evidence_from must be >= 2 readings, got {evidence_from}")
        self.evidence_from = None if evidence_from is None else int(evidence_from)
        self.relax = [dict(o) for o in (RELAXED_STAGES if relax is None else relax)]
        if not self.relax:
            raise ValueError("relax needs at least one stage of model options")
        self.stage = 0  # index into [given model, *relax]
        self.misfit_z: float | None = None
        self.log_evidence_ratio: float | None = None
        self._alternatives: dict[int, InverseSqrtPeakModel] = {}
        self.beta = float(beta)
        self.step_limit = None if step_limit is None else float(step_limit)
        self.n_starts = int(n_starts)
        if int(exploit_every) < 0:
            raise ValueError(f"exploit_every must be >= 0, got {exploit_every}")
        self.exploit_every = int(exploit_every)
        if int(info_every) < 0:
            raise ValueError(f"info_every must be >= 0, got {info_every}")
        self.info_every = int(info_every)
        self.adapt_box = bool(adapt_box)
        if self.adapt_box:
            if self.step_limit is None:
                raise ValueError("adapt_box needs a step_limit (the largest half-width)")
            if not 0 < float(min_step_limit) <= self.step_limit:
                raise ValueError(
                    f"min_step_limit must lie in (0, step_limit={self.step_limit}], "
                    f"got {min_step_limit}"
                )
            if int(success_streak) < 1 or int(failure_streak) < 1:
                raise ValueError("success_streak and failure_streak must be >= 1")
        self.min_step_limit = float(min_step_limit)
        self.success_streak, self.failure_streak = int(success_streak), int(failure_streak)
        tol = 0.25 * self.model.noise if success_tol is None else float(success_tol)
        if not (tol >= 0 and math.isfinite(tol)):
            raise ValueError(f"success_tol must be >= 0 and finite, got {success_tol}")
        self.success_tol = tol
        self.box_half_width = self.step_limit  # current half-width (adapted if adapt_box)
        self._streak = 0  # > 0: successes in a row, < 0: failures in a row
        self._best_mean: float | None = None
        self.seed = int(seed)
        self.travel_limit = _travel_limit(travel_limit, self.dim)
        self.last_info: dict = {}

    def trust_box(self, center: torch.Tensor) -> torch.Tensor:
        """The ``2 x d`` search box of the current half-width around ``center`` (same rule as
        :class:`BayesOpt`)."""
        return trust_box(self.bounds, center, self.box_half_width)

    def search_box(self, center: torch.Tensor) -> torch.Tensor:
        """The ``2 x d`` box the acquisition is maximized in: :meth:`trust_box` of ``center``,
        within ``travel_limit`` of the last told point when a travel limit is set."""
        box = self.trust_box(center)
        if self.travel_limit is None:
            return box
        half = self.travel_limit * (self.bounds[1] - self.bounds[0]) / 2
        travel = torch.stack(
            [torch.maximum(self.bounds[0], self.X[-1] - half),
             torch.minimum(self.bounds[1], self.X[-1] + half)]
        )  # fmt: skip
        lower, upper = torch.maximum(box[0], travel[0]), torch.minimum(box[1], travel[1])
        apart = lower > upper
        return torch.stack(
            [torch.where(apart, travel[0], lower), torch.where(apart, travel[1], upper)]
        )

    def _adapt(self, best_mean: float) -> None:
        """One TuRBO-like update of :attr:`box_half_width` from the best posterior mean."""
        if self._best_mean is not None:
            success = best_mean > self._best_mean + self.success_tol
            if success:
                self._streak = max(self._streak, 0) + 1
            else:
                self._streak = min(self._streak, 0) - 1
            if self._streak >= self.success_streak:
                self.box_half_width = min(2 * self.box_half_width, self.step_limit)
                self._streak = 0
            elif -self._streak >= self.failure_streak:
                self.box_half_width = max(self.box_half_width / 2, self.min_step_limit)
                self._streak = 0
        self._best_mean = best_mean if self._best_mean is None else max(best_mean, self._best_mean)

    def acquisition(self, X: torch.Tensor, beta: float | None = None) -> torch.Tensor:
        r""":math:`\mu + \sqrt\beta\,\sigma` at ``n x d`` settings (after a fit)."""
        mu, sd = self.model.predict(X)
        beta = self.beta if beta is None else beta
        return mu + math.sqrt(beta) * sd if beta > 0 else mu

    def misfit(self, X: torch.Tensor, Y: torch.Tensor) -> tuple[float, float, int]:
        r"""``(z, chi2, nu)`` of the fitted form at the told ``X``, ``Y`` (see ``prior_check``)."""
        with torch.no_grad():
            r = (Y - self.model.form(X)) / self.model.noise
        nu = max(len(Y) - self.model.n_params, 1)
        chi2 = float((r**2).sum())
        return (chi2 - nu) / math.sqrt(2.0 * nu), chi2, nu

    @property
    def relaxed(self) -> bool:
        """Whether the prior check has moved past the given model."""
        return self.stage > 0

    def _stage_model(self, stage: int) -> InverseSqrtPeakModel:
        """The (cached) model of ``relax[stage - 1]``, warm-started from the current fit."""
        if stage in self._alternatives:
            return self._alternatives[stage]
        options = {**self.model_options, **self.relax[stage - 1]}
        if "center_cov_scale_factor" in options:  # relative widening of the centre prior
            factor = float(options.pop("center_cov_scale_factor"))
            options["center_cov_scale"] = factor * float(
                self.model_options.get("center_cov_scale", 3.0)
            )
        if "shape_factor" in options:  # another scale of the given shape, as tight a prior
            factor = float(options.pop("shape_factor"))
            if not (math.isfinite(factor) and factor > 0):
                raise ValueError(f"shape_factor must be positive and finite, got {factor}")
            options["shape"] = factor * self._given_shape
        model = InverseSqrtPeakModel(self.prior, self.bounds, **options)
        model.theta = _extend_theta(self.model, model)
        self._alternatives[stage] = model
        return model

    def _check_prior(self, X: torch.Tensor, Y: torch.Tensor) -> None:
        """One step of ``prior_check``: misfit and evidence; on a rejection, move and notify."""
        last = len(self.relax)
        n_misfit = self.model.n_params + 5
        n_evidence = n_misfit if self.evidence_from is None else self.evidence_from
        if self.stage == last or len(Y) < min(n_misfit, n_evidence):
            return
        # The misfit (and its reported z) only from p + 5 readings, where its test applies.
        z = chi2 = nu = None
        if len(Y) >= n_misfit:
            z, chi2, nu = self.misfit(X, Y)
            self.misfit_z = z
        target, reasons, fitted = None, [], set()
        if z is not None and z > self.check_z:
            target = last
            reasons.append(
                f"the fitted physics form misses them by chi2/nu = {chi2 / nu:.2f} "
                f"(z = {z:.1f} > {self.check_z:g})"
            )
        elif len(Y) >= n_evidence and self.n_told % self.check_every == 0:
            here = self.model.log_evidence()
            ratios = {}
            for stage in range(self.stage + 1, last + 1):
                model = self._stage_model(stage)
                model.fit(X, Y)
                fitted.add(stage)
                ratios[stage] = model.log_evidence() - here
            best = max(ratios, key=ratios.get)
            self.log_evidence_ratio = ratios[best]
            if ratios[best] > self.evidence_margin:
                target = best
                lead = f"+{ratios[best]:.1f} > {self.evidence_margin:g}"
                reasons.append(f"stage {best}'s model explains them better (log evidence {lead})")
        if target is None:
            return
        model = self._stage_model(target)
        if target not in fitted:
            model.fit(X, Y)
        self.model, self.stage = model, target
        self._alternatives = {k: v for k, v in self._alternatives.items() if k > target}
        z_after, chi2_after, nu_after = self.misfit(X, Y)
        if len(Y) >= n_misfit:
            self.misfit_z = z_after
        freed = describe_stage(self.relax[target - 1])
        self.notify(
            "prior_rejected",
            f"physics prior rejected after {len(Y)} readings: "
            + "; ".join(reasons)
            + f"; stage {target} of {last} from now on ({freed}; chi2/nu = "
            f"{chi2_after / nu_after:.2f} after)",
            stage=target,
            z=z,
            chi2=chi2,
            nu=nu,
            n=len(Y),
            log_evidence_ratio=self.log_evidence_ratio,
        )

    def acquisition_with_grad(
        self, X: torch.Tensor, beta: float | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`acquisition` at ``n x d`` settings and its ``n x d`` gradient in closed form
        (:meth:`~pigp_torch.models.InverseSqrtPeakModel.predict_with_grad`)."""
        mu, sd, dmu, dsd = self.model.predict_with_grad(X)
        beta = self.beta if beta is None else beta
        if beta <= 0:
            return mu, dmu
        root = math.sqrt(beta)
        return mu + root * sd, dmu + root * dsd

    def centre_information(self, X: torch.Tensor) -> torch.Tensor:
        r"""Reduction of :math:`\mathrm{tr}(B\,C_\mu)` by one more reading at each of ``n x d``
        settings (after a fit), :math:`C_\mu` the Laplace covariance of the fitted centre.

        With :math:`C` the covariance of :math:`\theta`, :math:`\mathbf j = \partial f /
        \partial\theta` at the setting and :math:`\mathbf v = C\mathbf j`, a reading of noise
        :math:`\sigma_n` updates :math:`C \to C - \mathbf v\mathbf v^\top / (\sigma_n^2 +
        \mathbf j^\top C \mathbf j)` (Sherman-Morrison), so the trace falls by
        :math:`\mathbf v_\mu^\top B\, \mathbf v_\mu / (\sigma_n^2 + \mathbf j^\top C
        \mathbf j)`. Differentiable (torch); the ask maximizes the same quantity with its
        closed-form gradient,
        :meth:`~pigp_torch.models.InverseSqrtPeakModel.centre_information_with_grad`."""
        model = self.model
        J = model.jacobian(X)
        V = J @ model.cov
        Vmu = V[..., : model.dim]
        return ((Vmu @ model.shape()) * Vmu).sum(-1) / (model.noise**2 + (V * J).sum(-1))

    def ask(self) -> torch.Tensor:
        """Fit the physics form to all data, maximize the UCB in the trust box; returns ``d``."""
        if not self.Y:
            raise RuntimeError("no measurements yet: tell() the start point first")
        X = torch.stack(self.X)
        Y = torch.tensor(self.Y, dtype=DTYPE)
        t0 = time.perf_counter()
        self.model.fit(X, Y)
        if self.prior_check:
            self._check_prior(X, Y)
        with torch.no_grad():
            mean, _ = self.model.predict(X)
        center = X[int(mean.argmax())]
        if self.adapt_box:
            self._adapt(float(mean.max()))
        box = self.search_box(center)
        fitted = self.model.center()
        t1 = time.perf_counter()
        exploit = self.exploit_every > 0 and self.n_told % self.exploit_every == 0
        inform = not exploit and self.info_every > 0 and self.n_told % self.info_every == 0
        beta = 0.0 if exploit else self.beta
        x, value = find_optimum(
            self.model.centre_information_with_grad
            if inform
            else (lambda Z: self.acquisition_with_grad(Z, beta)),
            box,
            n_starts=self.n_starts,
            seed=self.seed + self.n_told,
            x_init=torch.stack([center, torch.minimum(torch.maximum(fitted, box[0]), box[1])]),
            maxiter=200,
            with_grad=True,
        )
        x = torch.minimum(torch.maximum(x, box[0]), box[1])  # guard against round-off
        self.last_info = {
            "center": center.clone(),
            "fitted_center": fitted,
            "fitted_peak": self.model.peak(),
            "acq_value": float(value),
            "exploit": exploit,
            "inform": inform,
            "trust_lower": box[0].clone(),
            "trust_upper": box[1].clone(),
            "box_half_width": self.box_half_width,
            "misfit_z": self.misfit_z,
            "log_evidence_ratio": self.log_evidence_ratio,
            "relaxed": self.relaxed,
            "fit_time_s": t1 - t0,
            "acq_time_s": time.perf_counter() - t1,
        }
        return x


def relaxed_stages(log_beta_std: float = 3.0, f_inf_std: float = 0.1) -> tuple[dict, dict]:
    """The two stages of the prior check after the given model, as model options over the
    given ones: first the shape's overall scale (``log_beta_std``, in log units) and the
    background (``f_inf_std``, relative) free; then also the shape's eigen-scales
    (``shape_std = 1``) and a centre prior 4x wider in variance
    (``center_cov_scale_factor`` multiplies the given ``center_cov_scale``)."""
    free = {"log_beta_std": float(log_beta_std), "f_inf_std": float(f_inf_std)}
    return free, {**free, "shape_std": 1.0, "center_cov_scale_factor": 4.0}


#: A broader-shape hypothesis: the given shape :math:`B` divided by 3 (``shape_factor``
#: multiplies it), with the given, tight prior on its scale. Against the given model it pays
#: no Occam factor (the same parameters, the same prior widths), so the evidence prefers it as
#: soon as the readings do, where the wide-scale stage must first earn its wider prior. Only
#: the broader side is a stage: a shape too narrow is the case the fit cannot leave by itself
#: (a narrow shape fits the readings as a lower, nearer peak), while a shape too broad already
#: shows in the residuals and the wide-scale stage.
BROADER_SHAPE = {"shape_factor": 1 / 3}

#: The stages of :class:`PhysicsModelBO`'s prior check after the given model:
#: :data:`BROADER_SHAPE`, then the two of :func:`relaxed_stages` (its defaults).
RELAXED_STAGES = (BROADER_SHAPE, *relaxed_stages())


#: Words for the stage options in a notice (an operator reads them in the progress line).
_STAGE_WORDS = {
    "shape_factor": "the given shape x {:.3g} (peak broader when < 1)",
    "log_beta_std": "shape scale fitted (log std {:g})",
    "f_inf_std": "background fitted (relative std {:g})",
    "shape_std": "shape eigen-scales fitted (log std {:g})",
    "center_cov_scale_factor": "centre prior {:g}x wider in variance",
}


def describe_stage(options: dict) -> str:
    """A prior-check stage's options in words, e.g. ``{"shape_factor": 1/3}`` ->
    ``"the given shape x 0.333 (peak broader when < 1) [shape_factor = 0.333333]"``; options
    without words are given as ``key = value``. Each item ends with its option and value."""
    items = []
    for key, value in options.items():
        number = isinstance(value, (int, float))
        raw = f"{key} = {value:g}" if number else f"{key} = {value}"
        words = _STAGE_WORDS.get(key) if number else None
        items.append(raw if words is None else f"{words.format(value)} [{raw}]")
    return ", ".join(items)


def _extend_theta(old: InverseSqrtPeakModel, new: InverseSqrtPeakModel) -> torch.Tensor:
    r"""``old``'s fitted :math:`\theta` laid out for ``new`` (a background and shape
    log-scales that ``old`` did not fit start at 0)."""
    d, theta = old.dim, old.theta
    out = new.prior_theta().clone()
    out[: d + 2] = theta[: d + 2]
    ratio = float(torch.trace(old.B) / torch.trace(new.B))
    if ratio != 1.0:  # a rescaled shape: keep beta B, the fitted curvature
        out[d + 1] = out[d + 1] + math.log(ratio)
    if old.f_inf_std > 0 and new.f_inf_std > 0:
        out[d + 2] = theta[d + 2]
    if old.shape_std > 0 and new.shape_std > 0:
        out[new._s_index :] = theta[old._s_index :]
    return out


def _travel_limit(value, d: int) -> torch.Tensor | None:
    """``None`` or a ``d`` tensor of positive finite fractions of the half-range."""
    if value is None:
        return None
    t = torch.as_tensor(value, dtype=DTYPE).reshape(-1)
    if t.numel() == 1:
        t = t.expand(d).clone()
    if t.numel() != d or not bool(torch.isfinite(t).all() and (t > 0).all()):
        raise ValueError(f"travel_limit must be positive and finite, one value or {d}: {value}")
    return t


def _choose(choice: str, what: str, own: str, ensemble_value, option: str, options: dict) -> str:
    """Resolve ``"auto" | "ensemble" | own`` for one ensemble field of the prior: puts the
    ensemble's value into ``options[option]`` (unless given there) or removes it; returns
    ``"ensemble"`` or ``own``, whichever the model gets."""
    if choice not in ("auto", "ensemble", own):
        raise ValueError(f"{what} must be auto, ensemble or {own}, got {choice!r}")
    if choice == "ensemble" and ensemble_value is None:
        raise ValueError(
            f"{what}='ensemble' needs a prior from an error ensemble (pigp build-prior "
            "--center-ensemble N, or benchmark.model_prior(center_ensemble=N))"
        )
    if choice == own:
        options.pop(option, None)
    elif ensemble_value is not None:
        options.setdefault(option, ensemble_value)
    return own if options.get(option) is None else "ensemble"
