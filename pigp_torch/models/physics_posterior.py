r"""The online-fitted physics form with its residual GP, and its prior check, as a posterior.

:class:`PhysicsFormPosterior` is the :class:`~pigp_torch.models.posterior.Posterior` of
:class:`~pigp_torch.models.inverse_sqrt.InverseSqrtPeakModel`: at every fit the form
:math:`f = f_\infty + (c + \beta(\mathbf x - \boldsymbol\mu)^\top B(\mathbf x -
\boldsymbol\mu))^{-1/2}` is fitted to all readings, the residual GP conditioned on what it
misses, and the *prior check* tests whether the physics prior still explains the readings
(moving, for good, to broader models when it does not). Mean and standard deviation with their
closed-form gradients (orders 0 and 1), and the information about the fitted centre that one
more reading gives (:meth:`PhysicsFormPosterior.centre_information`).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from pigp_torch.models._centre_design import expected_information
from pigp_torch.models.forgetting import Forgetting
from pigp_torch.models.inverse_sqrt import InverseSqrtPeakModel
from pigp_torch.models.posterior import PosteriorBase, Prediction
from pigp_torch.prior import PhysicsPrior


class PhysicsFormPosterior(PosteriorBase):
    r"""The physics form fitted online, with the prior check (see the module docstring).

    Args:
        prior: the model ring's physics prior (shape :math:`B`, :math:`f_\infty`, noise).
        bounds: ``2 x d`` knob bounds.
        center_prior: ``"ensemble"`` (:attr:`prior.center_cov`), ``"box"`` (isotropic,
            ``center_std`` half-ranges) or ``"auto"`` (the ensemble when the prior has one).
        shape_prior: ``"ensemble"`` (:attr:`prior.peak_shape`), ``"model"`` (:math:`2 c_m
            \Sigma`) or ``"auto"`` (the ensemble's when the prior has one).
        prior_check, check_z, evidence_margin, check_every, evidence_from, relax: the prior
            check, see :class:`~pigp_torch.optimizers.physics_bo.PhysicsModelBO`.
        forgetting: the learned memory of a drifting machine
            (:class:`~pigp_torch.models.forgetting.Forgetting`): ``True`` (default) its
            defaults, a dict its options, ``False`` none (every reading counts for good).
            With a learned log-height slope :math:`s \ne 0` the fit sees the remembered
            readings' part above the fitted background brought to the latest reading
            (:meth:`~pigp_torch.models.forgetting.Forgetting.rescale`).
        **model_options: :class:`~pigp_torch.models.InverseSqrtPeakModel` options.
    """

    max_order = 1

    def __init__(
        self,
        prior: PhysicsPrior,
        bounds,
        *,
        center_prior: str = "auto",
        shape_prior: str = "auto",
        prior_check: bool = True,
        check_z: float = 4.0,
        evidence_margin: float = 1.5,
        check_every: int = 3,
        evidence_from: int | None = 10,
        relax=None,
        forgetting: bool | dict = True,
        **model_options,
    ) -> None:
        on = forgetting is not False
        self.forgetting = Forgetting(**(forgetting if isinstance(forgetting, dict) else {}))
        self.forgetting = self.forgetting if on else None
        self.center_prior = _choose(center_prior, "center_prior", "box", prior.center_cov,
                                    "center_cov", model_options)  # fmt: skip
        self.shape_prior = _choose(shape_prior, "shape_prior", "model", prior.peak_shape,
                                   "shape", model_options)  # fmt: skip
        self.model = InverseSqrtPeakModel(prior, bounds, **model_options)
        self.bounds = self.model.bounds
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
        self._notices: list[dict] = []

    # -- the posterior protocol -----------------------------------------------------------------
    def observe(self, x: torch.Tensor, y: float) -> None:
        """Step detection on the new reading's innovation (``forgetting``)."""
        if self.forgetting is not None and self.forgetting.observe(self.model, x, y):
            self._notices.extend(self.forgetting.notices)
            self.forgetting.notices.clear()

    def fit(self, X: torch.Tensor, Y: torch.Tensor) -> None:
        """Fit the form to the remembered readings of ``X: n x d``, ``Y: n`` (all of them while
        no drift is found) with their weights, then run the prior check."""
        memory, w = self.forgetting, None
        if memory is not None:
            if memory.due(len(Y)):
                memory.select(self.model, X, Y)
            first, w = memory.weights(len(Y))
            X, Y = (X, Y) if first == 0 else (X[first:], Y[first:])
            if memory.slope != 0.0:  # the part above the background, brought to now
                Y = memory.rescale(Y, float(self.model.background()))
        self.model.fit(X, Y) if w is None else self.model.fit(X, Y, weights=w)
        if self.prior_check:
            self._check_prior(X, Y)

    def train_mean(self, X: torch.Tensor) -> torch.Tensor:
        """Posterior mean at the told points ``X`` (``n``)."""
        with torch.no_grad():
            return self.model.predict(X)[0]

    def predict(self, X: np.ndarray, order: int = 0) -> Prediction:
        """Mean and standard deviation at ``X: N x d`` (and their gradients for ``order=1``)."""
        if order not in (0, 1):
            raise ValueError(f"the physics form gives orders 0 and 1, got {order}")
        mu, sd, dmu, dsd = self.model.predict_numpy(X)
        return Prediction(mu, sd) if order == 0 else Prediction(mu, sd, dmu, dsd)

    def centre_information(self, X: np.ndarray, order: int = 0):
        r"""Reduction of :math:`\mathrm{tr}(B\,C_\mu)` by one more reading at each of ``X: N x d``
        (:meth:`~pigp_torch.models.InverseSqrtPeakModel.centre_information_with_grad`): ``N``
        values, with ``order=1`` also their ``N x d`` gradients."""
        info, grad = self.model.centre_information_numpy(X)
        return info if order == 0 else (info, grad)

    def correlated_centre_information(self, X: np.ndarray, order: int = 0):
        r"""Reduction of :math:`\mathrm{tr}(B\,C_\mu)` by one more reading at each of ``X: N x
        d`` with the readings' errors correlated by the residual GP (the exact Sherman-Morrison
        update, :func:`~pigp_torch.models._centre_design.expected_information` with ``rank =
        0``): ``N`` values, with ``order=1`` also their ``N x d`` gradients."""
        info, grad = expected_information(self.model, X)
        return info if order == 0 else (info, grad)

    def expected_centre_information(
        self, X: np.ndarray, order: int = 0, rank: int = 3, kappa: float = 1.0
    ):
        r"""The correlated reduction of :math:`\mathrm{tr}(B\,C_\mu)` averaged over the Laplace
        posterior of :math:`\theta` by ``2 rank + 1`` sigma points along the centre's costliest
        directions (:func:`~pigp_torch.models._centre_design.expected_information`): ``N``
        values, with ``order=1`` also their ``N x d`` gradients."""
        info, grad = expected_information(self.model, X, rank, kappa)
        return info if order == 0 else (info, grad)

    def extra_starts(self, box: torch.Tensor) -> list[torch.Tensor]:
        """The fitted centre projected into ``box``."""
        return [torch.minimum(torch.maximum(self.model.center(), box[0]), box[1])]

    def info(self) -> dict:
        return {
            "fitted_center": self.model.center(),
            "fitted_peak": self.model.peak(),
            "misfit_z": self.misfit_z,
            "log_evidence_ratio": self.log_evidence_ratio,
            "relaxed": self.relaxed,
            "memory_readings": None if self.forgetting is None else self.forgetting.tau,
            "height_slope": None if self.forgetting is None else self.forgetting.slope,
        }

    def take_notices(self) -> list[dict]:
        notices, self._notices = self._notices, []
        return notices

    # -- the prior check ------------------------------------------------------------------------
    def misfit(self, X: torch.Tensor, Y: torch.Tensor) -> tuple[float, float, int]:
        r"""``(z, chi2, nu)`` of the fitted form at the told ``X``, ``Y`` (see ``prior_check``)."""
        with torch.no_grad():
            r = (Y - self.model.form(X)) / self.model.noise
        w = self.model.weights  # forgetting: the weighted chi2 on the weights' count
        nu = max((len(Y) if w is None else float(w.sum())) - self.model.n_params, 1)
        chi2 = float((r**2).sum()) if w is None else float((w * r**2).sum())
        return (chi2 - nu) / math.sqrt(2.0 * nu), chi2, nu

    @property
    def drifting(self) -> bool:
        """Whether the learned memory follows a drift (a finite memory, a detected step or a
        changing height)."""
        memory = self.forgetting
        return memory is not None and (
            memory.tau < math.inf or memory.origin > 0 or memory.slope != 0.0
        )

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
        # The misfit (and its reported z) only from p + 5 readings, where its test applies;
        # with forgetting, p + 5 remembered ones (the sum of the weights).
        w = self.model.weights
        n_kept = len(Y) if w is None else float(w.sum())
        z = chi2 = nu = None
        if n_kept >= n_misfit:
            z, chi2, nu = self.misfit(X, Y)
            self.misfit_z = z
        target, reasons, fitted = None, [], set()
        if z is not None and z > self.check_z:
            target = last
            reasons.append(
                f"the fitted physics form misses them by chi2/nu = {chi2 / nu:.2f} "
                f"(z = {z:.1f} > {self.check_z:g})"
            )
        elif len(Y) >= n_evidence and len(Y) % self.check_every == 0:
            here = self.model.log_evidence()
            ratios = {}
            for stage in range(self.stage + 1, last + 1):
                model = self._stage_model(stage)
                model.fit(X, Y, weights=self.model.weights)
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
            model.fit(X, Y, weights=self.model.weights)
        self.model, self.stage = model, target
        self._alternatives = {k: v for k, v in self._alternatives.items() if k > target}
        z_after, chi2_after, nu_after = self.misfit(X, Y)
        if n_kept >= n_misfit:
            self.misfit_z = z_after
        freed = describe_stage(self.relax[target - 1])
        self._notices.append(
            dict(
                kind="prior_rejected",
                message=f"physics prior rejected after {len(Y)} readings: "
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
        )


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
