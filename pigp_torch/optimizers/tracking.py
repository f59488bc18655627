r"""A fitted model that follows a machine which changes while it is tuned.

:class:`TrackingModelOptimizer` is :class:`~pigp_torch.optimizers.model_check.
CheckedModelOptimizer` (the unknowns of a differentiable model :math:`M(x, \theta)` fitted to
the observables, the ask the model's optimum in a trust region, a prior check of the fit) whose
prior check, when it fails, does not hand over to a model-free search for the rest of the run.
What the model does not explain goes to a **tracked offset of the observables** and control
returns to the model once it explains the readings again:

1. **State space.** After the check fails the unknowns are held at their last fit
   :math:`\hat\theta` and the observables are modelled as

   .. math:: o_t = M(x_t, \hat\theta) + b_t + v_t, \qquad b_t = b_{t-1} + w_t,

   :math:`w_t \sim N(0, q s^2 I)` (a random walk: the drift), :math:`v_t \sim N(0, r s^2 I)`
   (the reading's noise), :math:`s` the stated noise ``obs_sd``, time :math:`t` the readings
   told. The offset :math:`b` (``m``, observable units) is estimated by a Kalman filter
   (:class:`OffsetTracker`, exact for this linear-Gaussian model), one per pair :math:`(q, r)`
   of a small grid; the pair used is the one with the largest one-step-ahead predictive
   log-likelihood, discounted by ``discount`` per reading (the process and reading noise learned
   from the data; :math:`q = 0` is a static offset).
2. **The best setting from the current estimate.** Each ask is the optimum of the goal of
   :math:`M(x, \hat\theta) + \hat b_t` in the trust region around the current setting (the last
   reading's: a stale best reading does not hold the region), found as
   :class:`~pigp_torch.optimizers.model_fit.FittedModelOptimizer`'s ask. The region doubles
   after a reading the tracked model predicted (every standardized innovation within
   ``agree_sd``) or one better than the reading before, and halves otherwise (``trust_min``,
   ``trust_max`` kept: safety rules). :meth:`recommend` is that optimum now.
3. **Step detection.** A CUSUM of the standardized innovations
   :math:`z_{t,j} = \nu_{t,j} / \sqrt{S_{t,j}}` of the chosen filter,
   :math:`C_t = \max(0, C_{t-1} + \overline{z_t^2} - k)`, alarms when :math:`C_t > h`
   (``cusum_k``, ``cusum_h``); the filters then restart at the last residual (re-acquire), and a
   ``"step"`` notice says so.
4. **Return to the model.** Every reading the check's :math:`\chi^2` of the last
   ``check_window`` readings is computed for the model without the offset, and every
   ``refit_every`` readings for a refit of the unknowns to those readings only; when either
   passes (:math:`p \ge` ``check_alpha``) the model is trusted again (a ``"model-restored"``
   notice): the offset is dropped, the fit forgets the readings before that window, and the
   best setting is the best reading since.

While nothing fails the check the optimizer is exactly the checked model (same fits, same asks):
a machine the model explains is tuned as before. ``fallback="nm"`` or ``"bo"`` gives the checked
model's permanent hand-over instead.
"""

from __future__ import annotations

import math

import torch

from pigp_torch._utils import DTYPE
from pigp_torch.optimizers._least_squares import fit_with_restarts
from pigp_torch.optimizers.base import AskTellOptimizer
from pigp_torch.optimizers.model_check import CheckedModelOptimizer, chi2_check
from pigp_torch.optimizers.model_fit import FittedModelOptimizer
from pigp_torch.optimizers.track_filter import FORGET_GRID, UnknownsFilter, information

__all__ = ["OffsetTracker", "TrackingModelOptimizer"]

#: Random-walk variances per reading and reading-noise variances of the filters (units of the
#: stated noise squared).
Q_GRID: tuple[float, ...] = (0.0, 0.01, 0.1, 1.0, 10.0, 100.0)
R_GRID: tuple[float, ...] = (1.0, 4.0, 16.0, 64.0, 256.0)


class OffsetTracker:
    r"""Kalman filters of an offset :math:`b_t \in \mathbb R^m` that walks at random
    (module docstring, step 1), one per pair of ``q_grid`` x ``r_grid``.

    Each filter, in units of ``sd`` (:math:`z = e / s`): prediction :math:`P^- = P + q`, innovation
    :math:`\nu = z - \hat b`, :math:`S = P^- + r`, gain :math:`K = P^- / S`, update
    :math:`\hat b \leftarrow \hat b + K\nu`, :math:`P \leftarrow (1 - K) P^-` (each observable on
    its own). Score of a filter: :math:`\sum_t \gamma^{n-t} \log N(\nu_t; 0, S_t)` summed over
    observables; the filter used has the largest score.

    Args:
        m: observables.
        sd: the stated noise :math:`s` (observable units).
        q_grid, r_grid: variances of the walk per reading and of the reading's noise, units of
            :math:`s^2` (defaults :data:`Q_GRID`, :data:`R_GRID`).
        prior_sd: standard deviation of the offset before the first residual (units of :math:`s`,
            default 1e3: diffuse).
        discount: :math:`\gamma` of the score (default 0.97: a memory of about 30 readings).
        cusum_k, cusum_h: step detection's allowance and threshold (default 3, 25).

    Attributes:
        n: residuals seen; chosen: index of the filter used; steps: readings (``n``) of the alarms.
    """

    def __init__(
        self,
        m: int,
        sd: float,
        *,
        q_grid=Q_GRID,
        r_grid=R_GRID,
        prior_sd: float = 1e3,
        discount: float = 0.97,
        cusum_k: float = 3.0,
        cusum_h: float = 25.0,
    ) -> None:
        if not (sd > 0 and prior_sd > 0 and 0 < discount <= 1 and cusum_h > 0):
            raise ValueError("need sd > 0, prior_sd > 0, 0 < discount <= 1 and cusum_h > 0")
        qs = torch.as_tensor(q_grid, dtype=DTYPE).reshape(-1)
        rs = torch.as_tensor(r_grid, dtype=DTYPE).reshape(-1)
        if (qs < 0).any() or (rs <= 0).any() or not (len(qs) and len(rs)):
            raise ValueError("q_grid must be >= 0 and r_grid > 0, neither empty")
        self.q = qs.repeat_interleave(len(rs))[:, None]
        self.r = rs.repeat(len(qs))[:, None]
        self.sd = float(sd)
        self.prior_var = float(prior_sd) ** 2
        self.mean = torch.zeros(len(self.q), int(m), dtype=DTYPE)
        self.var = torch.full_like(self.mean, self.prior_var)
        self.score = torch.zeros(len(self.q), dtype=DTYPE)
        self.discount = float(discount)
        self.cusum_k, self.cusum_h = float(cusum_k), float(cusum_h)
        self.cusum = 0.0
        self.n = 0
        self.chosen = 0
        self.steps: list[int] = []

    @property
    def offset(self) -> torch.Tensor:
        """The chosen filter's estimate of :math:`b` (``m``, observable units)."""
        return self.mean[self.chosen] * self.sd

    @property
    def offset_sd(self) -> torch.Tensor:
        """Its posterior standard deviation (``m``, observable units)."""
        return self.var[self.chosen].sqrt() * self.sd

    @property
    def process(self) -> tuple[float, float]:
        """The chosen ``(q, r)`` (units of the stated noise squared)."""
        return float(self.q[self.chosen, 0]), float(self.r[self.chosen, 0])

    def update(self, e) -> dict:
        r"""Filter one residual ``e`` (``m``, observable units). Returns ``{"z": m`` standardized
        innovations of the filter used before this residual, ``"step": bool}``."""
        z = torch.as_tensor(e, dtype=DTYPE).reshape(-1) / self.sd
        var_pred = self.var + self.q
        S = var_pred + self.r
        nu = z - self.mean
        g = self.chosen
        z_std = nu[g] / S[g].sqrt()
        loglik = -0.5 * (nu.square() / S + torch.log(2 * math.pi * S)).sum(-1)
        self.score = self.discount * self.score + loglik
        gain = var_pred / S
        self.mean = self.mean + gain * nu
        self.var = (1 - gain) * var_pred
        self.n += 1
        step = False
        if self.n > 1:  # the first residual only sets the offset
            self.cusum = max(0.0, self.cusum + float(z_std.square().mean()) - self.cusum_k)
            if self.cusum > self.cusum_h:
                step = True
                self.steps.append(self.n)
                self.cusum = 0.0
                self.mean = z.expand_as(self.mean).clone()  # re-acquire at the last residual
                self.var = self.r.expand_as(self.var).clone()
        self.chosen = int(self.score.argmax())
        return {"z": z_std, "step": step}


class TrackingModelOptimizer(CheckedModelOptimizer):
    r"""A checked fitted model whose failed check starts tracking instead of a hand-over
    (module docstring).

    Args:
        bounds: ``2 x d`` knob bounds.
        fallback: ``"track"`` (default: the module docstring) or a fallback of
            :class:`CheckedModelOptimizer` (``"nm"``, ``"bo"``, a callable: its hand-over).
        forgets: the forgetting factors of the filter of the unknowns (default
            :data:`~pigp_torch.optimizers.track_filter.FORGET_GRID`).
        track_trust, track_trust_min, track_trust_max: the trust region while tracking (fraction
            of each knob's range; default 0.01, 0.002, 0.05).
        q_grid, r_grid, discount, cusum_k, cusum_h: :class:`OffsetTracker`'s.
        options: :class:`CheckedModelOptimizer` arguments (``check_window``, ``check_alpha``, ...,
            and :class:`FittedModelOptimizer`'s).

    Attributes:
        tracking: whether the tracking fit is on (after the first failed check).
        tracker: the :class:`OffsetTracker` of the tracking fit's residual (``None`` before).
        offset_on: whether the offset is added to the model (the tracking fit fails the check).
        n_tracked: readings told while tracking; n_restored: returns to the model alone.
    """

    name = "model-fit-tracking"

    def __init__(
        self,
        bounds,
        *,
        fallback="track",
        forgets=FORGET_GRID,
        track_trust: float = 0.01,
        track_trust_min: float = 0.002,
        track_trust_max: float = 0.05,
        q_grid=Q_GRID,
        r_grid=R_GRID,
        discount: float = 0.97,
        cusum_k: float = 3.0,
        cusum_h: float = 25.0,
        use_offset: bool = True,
        **options,
    ) -> None:
        self.use_offset = bool(use_offset)
        self.track = isinstance(fallback, str) and fallback == "track"
        super().__init__(bounds, fallback="nm" if self.track else fallback, **options)
        self.tracker_options = dict(
            q_grid=q_grid, r_grid=r_grid, discount=discount, cusum_k=cusum_k, cusum_h=cusum_h
        )
        OffsetTracker(1, 1.0, **self.tracker_options)  # check the options now
        if not (0 < track_trust_min <= track_trust <= track_trust_max):
            raise ValueError("need 0 < track_trust_min <= track_trust <= track_trust_max")
        self.forgets = tuple(forgets)
        self.filter: UnknownsFilter | None = None
        self.track_trust = (float(track_trust), float(track_trust_min), float(track_trust_max))
        self.tracking = False
        self.tracker: OffsetTracker | None = None
        self.offset_on = False
        self.n_tracked = 0
        self.n_restored = 0
        self._search_offset: torch.Tensor | None = None

    @property
    def offset(self) -> torch.Tensor | None:
        """The offset added to the model (``m``, observable units), ``None`` when off."""
        return self.tracker.offset if self.offset_on else None

    # -- the fit and the check ---------------------------------------------------------------

    def _fit(self) -> tuple[torch.Tensor, float]:
        """The checked model's fit; while tracking, the filter of the unknowns takes the new
        reading (:class:`~pigp_torch.optimizers.track_filter.UnknownsFilter`; cost NaN)."""
        if not self.tracking:
            return super()._fit()
        self.filter.update(self.X[-1], self.O[-1])
        return self.filter.u.clone(), float("nan")

    def _fall_back(self, chi2: float, dof: int, p: float, k: int) -> None:
        if not self.track:
            return super()._fall_back(chi2, dof, p, k)
        self.tracking, self.offset_on = True, self.use_offset
        X = torch.stack(self.X)
        H = information(self.model, X, self.center, self.half_width, self.u,
                        obs_sd=self.obs_sd, prior_sd=self.prior_sd)  # fmt: skip
        self.filter = UnknownsFilter(self.model, self.center, self.half_width, self.u, H=H,
                                     obs_sd=self.obs_sd, prior_sd=self.prior_sd,
                                     forgets=self.forgets)  # fmt: skip
        self.tracker = OffsetTracker(self.O[-1].numel(), self.obs_sd, **self.tracker_options)
        for e in self._residuals(k):  # the readings that failed the check start the filter
            self.tracker.update(e)
        self._failed = 0
        self.trust = self.track_trust[0]
        self.notify(
            "prior-check",
            f"the fitted model does not explain the readings (chi2 {chi2:.1f} for {dof} numbers "
            f"over the last {k} readings, p = {p:.1e} < {self.check_alpha:g}, "
            f"{self.check_patience} checks in a row): its unknowns are tracked with forgetting "
            f"and its misfit as an offset of the observables",
            chi2=chi2,
            dof=dof,
            p=p,
        )

    def _residuals(self, k: int) -> torch.Tensor:
        """``k x m``: the last ``k`` readings minus the fitted model (no offset)."""
        X, O = torch.stack(self.X[-k:]), torch.stack(self.O[-k:])
        with torch.no_grad():
            return O - self.model(X, self.theta.detach())

    def tell(self, x, y: float, observables=None) -> None:
        """The checked model's tell (fit and check); while tracking: record and fit the last
        readings, filter the new residual, resize the trust region, detect a step, check."""
        if not self.tracking:
            super().tell(x, y, observables=observables)
            return
        o = torch.as_tensor(observables, dtype=DTYPE).reshape(-1)
        with torch.no_grad():
            pred = self.model(self._check_point(x)[None], self.theta.detach())[0]
        if self.offset_on:
            pred = pred + self.tracker.offset
        agree = bool(((o - pred).abs() <= self.agree_sd * self.obs_sd).all())
        y_prev, trust = self.Y[-1], self.trust
        FittedModelOptimizer.tell(self, x, y, observables=observables)
        self.n_tracked += 1
        info = self.tracker.update(self._residuals(1)[0])
        better = y > y_prev if self.maximize else y < y_prev
        _, lo, hi = self.track_trust
        self.trust = min(2 * trust, hi) if agree or better else max(trust / 2, lo)
        if info["step"]:
            shift = float((self.tracker.offset.abs() / self.obs_sd).max())
            self.notify(
                "step",
                f"a step change: the readings left the tracked model (CUSUM of the standardized "
                f"innovations over {self.tracker.cusum_h:g}); the offset re-acquired at the last "
                f"reading ({shift:.1f} noise sd from the model)",
            )
        self._check_tracking()

    def _check_tracking(self) -> None:
        """The prior check of the tracking fit on the last ``check_window`` readings: passing,
        the model alone is asked (the offset dropped); failing ``check_patience`` times in a row,
        the offset is added again."""
        k = min(self.check_window, self.n_told)
        X, O = torch.stack(self.X[-k:]), torch.stack(self.O[-k:])
        chi2, dof, p = chi2_check(self.model, X, O, self.theta.detach(), self.obs_sd)
        self.checks.append({"at_told": self.n_told, "chi2": chi2, "dof": dof, "p": p})
        self._failed = self._failed + 1 if p < self.check_alpha else 0
        if self.offset_on and p >= self.check_alpha:
            self.offset_on = False
            self.n_restored += 1
            self.notify(
                "model-restored",
                f"the tracked model explains the last {k} readings again (chi2 {chi2:.1f} for "
                f"{dof} numbers, p = {p:.1e}): its optimum is asked without the offset",
                chi2=chi2,
                dof=dof,
                p=p,
            )
        elif self.use_offset and not self.offset_on and self._failed >= self.check_patience:
            self.offset_on = True
            self.notify(
                "prior-check",
                f"the tracked model does not explain the last {k} readings (chi2 {chi2:.1f} for "
                f"{dof} numbers, p = {p:.1e}): its misfit is added as an offset again",
                chi2=chi2,
                dof=dof,
                p=p,
            )

    # -- the ask -------------------------------------------------------------------------------

    def best(self) -> tuple[torch.Tensor, float]:
        """The checked model's best setting; while tracking, the best reading (a best setting
        of the past is not the best now: :meth:`recommend` is)."""
        if self.tracking:
            return AskTellOptimizer.best(self)
        return super().best()

    def _search_box(self) -> torch.Tensor:
        """While tracking, the trust region around the current setting (the last reading's)."""
        if not self.tracking:
            return super()._search_box()
        lo, hi = self.bounds
        half = self.trust * (hi - lo)
        x = self.X[-1]
        return torch.stack([torch.maximum(lo, x - half), torch.minimum(hi, x + half)])

    def _fit_change(self, theta: torch.Tensor) -> float:
        """The change of the prediction at the last ask since the last search (noise sd), the
        offset's change included."""
        change = super()._fit_change(theta)
        now, then = self.offset, self._search_offset
        if (now is None) != (then is None):
            return float("inf")
        if now is not None:
            change += float((now - then).abs().max()) / self.obs_sd
        return change

    def ask(self) -> torch.Tensor:
        """The checked model's ask; while tracking, the optimum of the model plus the tracked
        offset in the trust region around the current setting."""
        offset = self.offset
        if offset is None:
            x = super().ask()
            self._search_offset = None
            return x
        base = self.model

        def model(X: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
            return base(X, theta) + offset

        self.model = model
        try:
            x = FittedModelOptimizer.ask(self)
        finally:
            self.model = base
        self._search_offset = offset
        return x

    def recommend(self) -> torch.Tensor:
        """The setting the model puts the optimum at now (``d``): while tracking, the ask (the
        optimum of the tracked model, plus the offset while it is on, around the current
        setting); before, :meth:`best`'s setting (the one-shot behaviour)."""
        return self.ask() if self.tracking else self.best()[0]

    def tracked(self) -> dict[str, tuple[float, str]]:
        """The tracked quantities: ``{name: (value, unit)}``: the fitted unknowns (held while
        tracking) and the offset of each observable (0 while the model alone is trusted)."""
        mm = self.machine_model
        P = self.center.numel()
        names = list(mm.unknown_names) if mm is not None else [f"u{i}" for i in range(P)]
        units = list(mm.unknown_units) if mm is not None else [""] * P
        out = {n: (float(v), u) for n, v, u in zip(names, self.theta, units, strict=True)}
        if not self.O:
            return out
        m = self.O[-1].numel()
        obs = list(mm.observable_names) if mm is not None else [f"o{j}" for j in range(m)]
        obs_units = list(mm.observable_units) if mm is not None else [""] * m
        off = self.offset if self.offset is not None else torch.zeros(m, dtype=DTYPE)
        for n, v, u in zip(obs, off, obs_units, strict=True):
            out[f"{n}_offset"] = (float(v), u)
        return out
