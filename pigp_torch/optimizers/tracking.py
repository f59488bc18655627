r"""A fitted model that follows a machine which changes while it is tuned.

:class:`TrackingModelOptimizer` is :class:`~pigp_torch.optimizers.model_check.
CheckedModelOptimizer` (the unknowns :math:`\theta` of a differentiable model :math:`M(x, \theta)`
fitted to every reading's observables, the ask the model's optimum in a trust region, a prior
check of the fit) whose prior check, when it fails, does not hand the run over to a model-free
search: from then on the model **follows the machine**.

1. **Tracked unknowns and a residual on the observables.** The state is the unknowns and an
   offset :math:`b \in \mathbb R^m` of the observables (what the model does not explain:
   physics it lacks, acting fields that differ from the set ones),

   .. math:: o_t = M(x_t, \theta_t) + b_t + v_t, \qquad v_t \sim N(0, s^2 I),

   fitted by :class:`~pigp_torch.optimizers.track_filter.UnknownsFilter`: an information filter
   that forgets old readings at a rate learned from the one-step-ahead predictive likelihood
   (time: the readings told), relinearized every ``refit_every`` readings at the weighted batch
   fit of all readings (a nonlinear model's old linearizations mislead it). It starts from the
   checked model's fit and information, the offset at 0 with the prior half width
   ``offset_half_width`` (observable units, default 50 ``obs_sd``), and the checked model's
   noise: at the first failed check the setting is read again (``noise_probe`` times, default
   2: :class:`~pigp_torch.optimizers.model_check.CheckedModelOptimizer`), and a scatter of the
   repeats above the stated noise becomes the noise :math:`s` of the fit and of the filter. A
   machine that drifts between two readings reads part of its drift as noise; a screen that
   jitters more than stated is otherwise chased reading by reading (the filter then learns a
   fast forgetting and the asks follow the jitter).
2. **The acting fields from the optimizer's own setpoints.** Magnets with play (backlash) act
   with :math:`y_t = x_t + h_t` where the offset :math:`h_t \in [-w, w]` follows the setpoint
   path (:mod:`pigp_torch.optimizers.play`: a move past the play drags the field behind the
   setpoint, a smaller one leaves it). The play half widths :math:`w` (one per knob) and the
   offsets before the run are unknowns of the filter too (prior centred at 0 with half width
   ``play_half_width`` of each knob's range, default 0.005; :math:`w = 0` is a magnet without
   play; ``play_half_width=0``: no play modelled), the model reads the acting fields
   :math:`M(x_t + h_t(w), \theta_t)`, and the search of the ask is over the acting fields, the ask
   the setpoint that makes them from the present state (past the play in the direction of the
   move; a knob asked to move by less than its play is held when the model loses less than
   ``PLAY_HOLD`` noise sd by it). Whether there is play at all is learned
   (:meth:`~pigp_torch.optimizers.tracking_play.PlayState._choose_play`: the fits with and
   without it predicting the last readings; until the play is taken up the acting fields are
   the setpoints, and the filter starts from the batch fit with play once it is). A law other
   than the play enters as what the offset and the forgetting absorb.
3. **The best setting from the current estimate.** Each ask is the optimum of the goal of
   :math:`M(x, \hat\theta_t) + \hat b_t` in the trust region around the current setting (the last
   reading's: a stale best reading does not hold it), found as :class:`~pigp_torch.optimizers.
   model_fit.FittedModelOptimizer`'s ask. The region doubles after a reading the filter
   predicted (every standardized innovation within ``agree_sd``) or one better than the reading
   before, and halves otherwise, within ``track_trust_min``, ``track_trust_max`` (fractions of
   each knob's range: the travel per reading is a safety rule). :meth:`recommend` is that
   optimum now, unless the recent readings scatter more than stated (then the recent reading
   with the best GP posterior mean: :meth:`recommend`).
4. **Step detection.** A CUSUM of the filter's standardized innovations :math:`z_t`,
   :math:`C_t = \max(0, C_{t-1} + \overline{z_t^2} - k)`, alarms above :math:`h` (``cusum_k``,
   ``cusum_h``): the filter then forgets what it learned from the readings before
   (``step_forget``) and re-acquires from the next ones; a ``"step"`` notice says so.
5. **What is left, optionally.** With ``residual_gp=True`` a GP of the residuals of the last
   readings (:mod:`~pigp_torch.optimizers.residual_gp`) is added to the model the ask optimizes,
   before and while tracking, whenever it explains them better than noise.
6. **The check returns to the model.** The prior check keeps running on the tracked model; the
   model is never abandoned, and the ``"model-restored"`` notice says when it explains the last
   ``check_window`` readings again.

While the check passes the optimizer is exactly the checked model (same fits, same asks): a
machine the model explains is tuned as before. ``fallback="nm"`` or ``"bo"`` gives the checked
model's permanent hand-over instead.
"""

from __future__ import annotations

import torch

from pigp_torch._utils import DTYPE
from pigp_torch.optimizers.base import AskTellOptimizer
from pigp_torch.optimizers.estimate import posterior_fit
from pigp_torch.optimizers.model_check import CheckedModelOptimizer, chi2_check
from pigp_torch.optimizers.model_fit import AGREE_SD, FittedModelOptimizer
from pigp_torch.optimizers.residual_gp import ResidualGP, tracker_residual_gp
from pigp_torch.optimizers.track_filter import FORGET_GRID, UnknownsFilter, information
from pigp_torch.optimizers.tracking_play import PlayState

__all__ = ["END_NOISE", "END_WINDOW", "TrackingModelOptimizer"]

#: :meth:`TrackingModelOptimizer.recommend` while tracking: the last readings it looks at, and
#: the multiple of the stated noise above which their scatter makes it choose among them.
END_WINDOW, END_NOISE = 10, 4.0


class TrackingModelOptimizer(PlayState, CheckedModelOptimizer):
    r"""A checked fitted model that follows the machine after a failed check (module
    docstring).

    Args:
        bounds: ``2 x d`` knob bounds.
        fallback: ``"track"`` (default: the module docstring) or a fallback of
            :class:`CheckedModelOptimizer` (``"nm"``, ``"bo"``, a callable: its hand-over).
        forgets: the filter's forgetting factors (default
            :data:`~pigp_torch.optimizers.track_filter.FORGET_GRID`).
        offset_half_width: prior half width of the observables' offset (observable units;
            default 50 ``obs_sd``; 0: no offset, the unknowns alone are tracked).
        play_half_width: prior half width of each knob's play, a fraction of its range
            (default 0.005; 0: no play modelled).
        refit_every: readings between relinearizations of the filter (default 5; 0: never,
            and no batch fit at the start without play: the first version's filter).
        track_trust, track_trust_min, track_trust_max: the trust region while tracking (fraction
            of each knob's range; default 0.01, 0.002, 0.05).
        cusum_k, cusum_h, step_forget: step detection (default 10, 100: a lag
            of a few noise sd does not alarm, a jump of 10 does at once) and the weight left to
            the readings before a step (default 0.01).
        end: :meth:`recommend` while tracking: ``"recent"`` (default: the best GP posterior
            mean among the recent readings when they scatter more than stated, else the optimum
            of the tracked model now) or ``"now"`` (always the optimum now).
        residual_gp: add a GP of the last readings' residuals to the model the ask optimizes
            (:mod:`~pigp_torch.optimizers.residual_gp`; default ``False``: on the static ARES
            gaps it moved the final by 0.01-1 µm either way, docs/results.md).
        options: :class:`CheckedModelOptimizer` arguments (``check_window``, ``check_alpha``, ...,
            and :class:`FittedModelOptimizer`'s).

    Attributes:
        tracking: whether the model follows the machine (after the first failed check).
        filter: the :class:`~pigp_torch.optimizers.track_filter.UnknownsFilter` (``None``
            before); steps: readings told at each step alarm; n_tracked: readings told while
            tracking; n_restored: "model-restored" notices.
        last_residual_gp: the residual GP of the last ask (``None``: none used);
            n_residual_asks: asks that used one.
    """

    name = "model-fit-tracking"

    def __init__(
        self,
        bounds,
        *,
        fallback="track",
        forgets=FORGET_GRID,
        offset_half_width: float | None = None,
        play_half_width: float = 0.005,
        refit_every: int = 5,
        track_trust: float = 0.01,
        track_trust_min: float = 0.002,
        track_trust_max: float = 0.05,
        cusum_k: float = 10.0,
        cusum_h: float = 100.0,
        step_forget: float = 0.01,
        end: str = "recent",
        residual_gp: bool = False,
        **options,
    ) -> None:
        self.track = isinstance(fallback, str) and fallback == "track"
        super().__init__(bounds, fallback="nm" if self.track else fallback, **options)
        if not (0 < track_trust_min <= track_trust <= track_trust_max):
            raise ValueError("need 0 < track_trust_min <= track_trust <= track_trust_max")
        if not (cusum_h > 0 and 0 < step_forget <= 1):
            raise ValueError("need cusum_h > 0 and 0 < step_forget <= 1")
        self.forgets = tuple(forgets)
        half = 50 * self.obs_sd if offset_half_width is None else float(offset_half_width)
        if half < 0:
            raise ValueError(f"offset_half_width must be >= 0, got {offset_half_width}")
        self.offset_half_width = half
        if not play_half_width >= 0:
            raise ValueError(f"play_half_width must be >= 0, got {play_half_width}")
        lo, hi = self.bounds
        self._play_half = play_half_width * (hi - lo) if play_half_width > 0 else None
        self._play: tuple[torch.Tensor, ...] | None = None
        self._play_on = False
        self._n_off = 0
        self.refit_every = int(refit_every)
        self.track_trust = (float(track_trust), float(track_trust_min), float(track_trust_max))
        self.cusum_k, self.cusum_h, self.step_forget = float(cusum_k), float(cusum_h), step_forget
        if end not in ("recent", "now"):
            raise ValueError(f"end must be 'recent' or 'now', got {end!r}")
        self.end = end
        self.residual_gp = bool(residual_gp)
        self.last_residual_gp: ResidualGP | None = None
        self.n_residual_asks = 0
        self.tracking = False
        self.filter: UnknownsFilter | None = None
        self.steps: list[int] = []
        self.n_tracked = 0
        self.n_restored = 0
        self._cusum = 0.0
        self._search_offset: torch.Tensor | None = None
        self._search_gp = False

    @property
    def offset(self) -> torch.Tensor | None:
        """The tracked offset of the observables (``m``, observable units); ``None`` before
        tracking or without an offset."""
        if self.filter is None or self.offset_half_width == 0:
            return None
        P = self.center.numel()
        return self.filter.u[P : P + self._n_off] * self.offset_half_width

    def _fit(self) -> tuple[torch.Tensor, float]:
        """The checked model's fit; while tracking, the filter takes the new reading (cost
        NaN)."""
        if not self.tracking:
            return super()._fit()
        self._refresh_play()
        self.filter.update(self._rows(1)[0], self.O[-1])
        if self.refit_every and (self.n_tracked + 1) % self.refit_every == 0:
            self._refresh_play()
            n = len(self.X)
            weights = torch.ones(n, dtype=DTYPE)
            for step in self.steps:  # the readings before a step count step_forget
                weights[:step] *= self.step_forget
            if self._play is not None and not self._play_on:
                self._choose_play(weights)
            self.filter.refit(self._rows(n), torch.stack(self.O), weights)
        self._refresh_play()
        return self.filter.u[: self.center.numel()].clone(), float("nan")

    def _fall_back(self, chi2: float, dof: int, p: float, k: int) -> None:
        if not self.track:
            return super()._fall_back(chi2, dof, p, k)
        P, m, d = self.center.numel(), self.O[-1].numel(), self.dim
        base, n_off = self.model, (m if self.offset_half_width > 0 else 0)
        n_play = 2 * d if self._play_half is not None else 0
        self._n_off = n_off

        def model(X: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
            if n_play:  # the acting fields x + a + D w + E g (rows of _rows)
                w, g = theta[..., P + n_off : P + n_off + d], theta[..., P + n_off + d :]
                X = X[..., :d] + X[..., d : 2 * d] + X[..., 2 * d : 3 * d] * w + X[..., 3 * d :] * g
            out = base(X, theta[..., :P])
            return out + theta[..., P : P + n_off] if n_off else out

        H = information(self.model, torch.stack(self.X), self.center, self.half_width, self.u,
                        obs_sd=self.obs_sd, prior_sd=float(self.settings.prior_sd))  # fmt: skip
        H = torch.block_diag(H, torch.eye(n_off + n_play, dtype=DTYPE) / self.settings.prior_sd**2)
        zeros = torch.zeros(n_off + n_play, dtype=DTYPE)
        half = torch.full((n_off,), self.offset_half_width, dtype=DTYPE)
        if n_play:
            half = torch.cat([half, self._play_half, self._play_half])
        self.filter = UnknownsFilter(
            model,
            torch.cat([self.center, zeros]),
            torch.cat([self.half_width, half]),
            torch.cat([self.u, zeros]),
            H=H,
            obs_sd=self.obs_sd,
            prior_sd=float(self.settings.prior_sd),
            forgets=self.forgets,
        )
        self.tracking, self._failed = True, 0
        if n_play:
            self._refit_start()
        self.trust = self.track_trust[0]
        self.notify(
            "prior-check",
            f"the fitted model does not explain the readings (chi2 {chi2:.1f} for {dof} numbers "
            f"over the last {k} readings, p = {p:.1e} < {self.check_alpha:g}, "
            f"{self.check_patience} checks in a row): from now on its unknowns and an offset of "
            "the observables are tracked, forgetting old readings",
            chi2=chi2,
            dof=dof,
            p=p,
        )

    def tell(self, x, y: float, observables=None) -> None:
        """The checked model's tell (fit and check); while tracking: the filter's update, the
        trust region, step detection and the check of the tracked model."""
        if not self.tracking:
            super().tell(x, y, observables=observables)
            return
        y_prev, trust = self.Y[-1], self.trust
        FittedModelOptimizer.tell(self, x, y, observables=observables)  # the filter's update
        self.n_tracked += 1
        z = self.filter.last_z
        better = y > y_prev if self.maximize else y < y_prev
        _, lo, hi = self.track_trust
        grow = better or bool((z.abs() <= AGREE_SD).all())
        self.trust = min(2 * trust, hi) if grow else max(trust / 2, lo)
        self._cusum = max(0.0, self._cusum + float(z.square().mean()) - self.cusum_k)
        if self._cusum > self.cusum_h:
            self._cusum = 0.0
            self.steps.append(self.n_told)
            for g in range(len(self.filter.forgets)):
                self.filter.L[g] = self.step_forget * self.filter.L[g]
                self.filter.eta[g] = self.step_forget * self.filter.eta[g]
            self.notify(
                "step",
                f"a step change: the readings left the tracked model (CUSUM of the standardized "
                f"innovations over {self.cusum_h:g}); the fit forgets the readings before and "
                "re-acquires",
            )
        self._check_tracking()

    def _check_tracking(self) -> None:
        """The prior check of the tracked model (with its offset) on the last
        ``check_window`` readings; a notice when it passes again after failing."""
        k = min(self.check_window, self.n_told)
        X, O = self._rows(k), torch.stack(self.O[-k:])
        with torch.no_grad():
            chi2, dof, p = chi2_check(self.filter.model, X, O, self._filter_theta(), self.obs_sd)
        self.checks.append({"at_told": self.n_told, "chi2": chi2, "dof": dof, "p": p})
        failed_before = self._failed >= self.check_patience
        self._failed = self._failed + 1 if p < self.check_alpha else 0
        if failed_before and self._failed == 0:
            self.n_restored += 1
            self.notify(
                "model-restored",
                f"the tracked model explains the last {k} readings again (chi2 {chi2:.1f} for "
                f"{dof} numbers, p = {p:.1e})",
                chi2=chi2,
                dof=dof,
                p=p,
            )

    def _filter_theta(self) -> torch.Tensor:
        return self.filter.center + self.filter.half_width * self.filter.u

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
        x = self.X[-1] if self._used_play is None else self.X[-1] + self._used_play[0][-1]
        return torch.stack([torch.maximum(lo, x - half), torch.minimum(hi, x + half)])

    def _fit_change(self, theta: torch.Tensor) -> float:
        """The change of the prediction at the last ask since the last search (noise sd), the
        offset's change included."""
        if self.last_residual_gp is not None or self._search_gp:
            return float("inf")  # the residual GP moves with every reading
        change = super()._fit_change(theta)
        now, then = self.offset, self._search_offset
        if (now is None) != (then is None):
            return float("inf")
        if now is not None:
            change += float((now - then).abs().max()) / self.obs_sd
        return change

    def ask(self) -> torch.Tensor:
        """The checked model's ask; while tracking, the optimum of the model plus the tracked
        offset in the trust region around the current setting. With play the search is over
        the acting fields around the present ones, and the ask is the setpoint that makes the
        optimum's fields from the present state (:func:`~pigp_torch.optimizers.play.
        setpoint_for`: past the play in the direction of the move). With ``residual_gp``, in
        both, the residual GP of the last readings is added
        (:func:`~pigp_torch.optimizers.residual_gp.tracker_residual_gp`)."""
        offset = self.offset
        gp = tracker_residual_gp(self) if self.residual_gp else None
        self.last_residual_gp = gp
        if offset is None and self._used_play is None and gp is None:
            x = super().ask()
            self._search_offset, self._search_gp = None, False
            return x
        base = self.model

        def model(X: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
            out = base(X, theta)
            if offset is not None:
                out = out + offset
            return out + gp(X) if gp is not None else out

        self.model = model
        try:
            x = FittedModelOptimizer.ask(self)
            if self._used_play is not None:
                x = self._hold_small_moves(x)
        finally:
            self.model = base
        self._search_offset, self._search_gp = offset, gp is not None
        self.n_residual_asks += int(gp is not None)
        return x if self._used_play is None else self._setpoint_for_fields(x)

    def recommend(self) -> torch.Tensor:
        r"""The setting the evidence puts the optimum at (``d``). Before tracking, the checked
        model's (the one-shot behaviour). While tracking, the ask (the tracked model's optimum
        around the current setting) unless the readings scatter more than stated: when a GP on
        the scalar readings of the last :math:`k = \min(n_{tracked}, 10)` (``END_WINDOW``)
        readings fits them with a noise sd over ``END_NOISE`` times the stated noise
        (:func:`~pigp_torch.optimizers.estimate.posterior_fit`; the stated noise is of each
        observable, a goal such as a mean absolute error scatters by about as much), the model
        has been chasing single readings: the setpoint of the recent reading with the best GP
        posterior mean instead (noisy readings averaged; the setpoint as it was read, not
        through the learned play: noise can make a play of the magnets up, and a setting
        reached through a spurious play misses by twice its width). ``end="now"``: always the
        ask."""
        if not self.tracking:
            return super().recommend()
        k = min(self.n_tracked, END_WINDOW)
        if self.end == "now" or k < 3:
            return self.ask()
        X, Y = torch.stack(self.X[-k:]), torch.tensor(self.Y[-k:], dtype=DTYPE)
        i, noise = posterior_fit(X, Y, self.bounds, maximize=self.maximize, k=k)
        if noise <= END_NOISE * self.obs_sd:
            return self.ask()
        return self.X[len(self.X) - k + i].clone()
