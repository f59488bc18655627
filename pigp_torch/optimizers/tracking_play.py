r"""The play (backlash) part of :class:`~pigp_torch.optimizers.tracking.TrackingModelOptimizer`:
the acting fields of the readings from the optimizer's own setpoint path
(:mod:`pigp_torch.optimizers.play`), with the play widths and the offsets before the run among
the filter's unknowns (the tracker's module docstring, item 2).
"""

from __future__ import annotations

import torch

from pigp_torch._utils import DTYPE
from pigp_torch.optimizers._least_squares import fit_unknowns
from pigp_torch.optimizers.model_fit import FIT_ITER
from pigp_torch.optimizers.play import play_path, setpoint_for
from pigp_torch.optimizers.track_filter import information

__all__ = ["PLAY_EVIDENCE", "PLAY_EXPLAINS", "PLAY_HOLD", "PLAY_TOL", "PlayState"]

#: An acting field asked within this fraction of its knob's range of the present one is the
#: present one (no move: round-off does not reverse the play).
PLAY_TOL = 1e-6
#: Knobs asked to move by less than their play are held when the model's goal there is within
#: this many noise sd of the ask's.
PLAY_HOLD = 0.25
#: The play is used when the fit with it predicts the last readings better than the fit without
#: by this much per play unknown (squared noise sd) and by this fraction of the error without.
PLAY_EVIDENCE, PLAY_EXPLAINS = 2.0, 2 / 3


class PlayState:
    """Methods of the tracker's play state (a mixin of
    :class:`~pigp_torch.optimizers.tracking.TrackingModelOptimizer`: its readings ``X``, ``O``,
    ``filter``, ``_play_half`` and ``_play``; the unknowns of the filter end with the ``d`` play
    widths and the ``d`` offsets before the run)."""

    @property
    def play_width(self) -> torch.Tensor | None:
        """The tracked play half widths of the knobs (``d``, knob units, >= 0); ``None`` before
        tracking or without play."""
        if self.filter is None or self._play_half is None:
            return None
        f, d = self.filter, self.dim
        k = slice(-2 * d, -d)
        return (f.center[k] + f.half_width[k] * f.u[k]).clamp_min(0.0)

    def _refresh_play(self) -> None:
        """The play path of every reading's setpoint at the tracked widths (:func:`play_path`)."""
        if self._play_half is not None:
            w, f = self.play_width, self.filter
            g = (f.half_width[-self.dim :] * f.u[-self.dim :]).clamp(-w, w)
            self._play = (*play_path(torch.stack(self.X), w, g), w, g)

    @property
    def _used_play(self) -> tuple[torch.Tensor, ...] | None:
        """The play state when the play is used (:meth:`_choose_play`), else ``None``."""
        return self._play if self._play_on else None

    def _rows(self, k: int, on: bool | None = None) -> torch.Tensor:
        r"""The filter's inputs of the last ``k`` readings: the setpoints, with play also
        :math:`a_t = h_t - D_t \hat w - E_t \hat g`, :math:`D_t` and :math:`E_t` (``k x 4d``: the
        acting field :math:`x_t + a_t + D_t w + E_t g` is linear in the widths :math:`w` and the
        offsets :math:`g` before the run, :func:`~pigp_torch.optimizers.play.play_path`); while
        the play is not used (``on``, default :meth:`_choose_play`'s choice) zeros in their place:
        the acting fields are the setpoints."""
        X = torch.stack(self.X[-k:])
        if self._play is None:
            return X
        H, D, E, w, g = self._play
        if not (self._play_on if on is None else on):
            return torch.cat([X, torch.zeros(k, 3 * X.shape[1], dtype=X.dtype)], -1)
        a = H[-k:] - D[-k:] * w - E[-k:] * g
        return torch.cat([X, a, D[-k:], E[-k:]], -1)

    def _rows_at(self, n: int, u: torch.Tensor) -> torch.Tensor:
        """:meth:`_rows` of the last ``n`` readings with the play path at the widths and start
        offsets of the normalized unknowns ``u`` (the filter's layout)."""
        f, d = self.filter, self.dim
        theta = f.center + f.half_width * u
        w = theta[-2 * d : -d].clamp_min(0.0)
        g = torch.minimum(torch.maximum(theta[-d:], -w), w)
        H, D, E = play_path(torch.stack(self.X), w, g)
        a = H - D * w - E * g
        return torch.cat([torch.stack(self.X), a, D, E], -1)[-n:]

    def _choose_play(self, weights=None, holdout: int = 5) -> None:
        r"""Whether the play is used: the weighted batch fits (the filter's forgetting, reading
        weights ``weights``) with and without it of all readings but the last ``holdout``
        (with it: twice, the play path refreshed at the first fit's widths), scored by how well
        they predict those (the sum of the squared errors in noise sd). The play is taken up
        when it takes ``PLAY_EXPLAINS`` of the error without it away, and at least
        ``PLAY_EVIDENCE`` per play unknown (a law other than the play, or none, does not buy its
        unknowns, which then fit the past only in part); once used it is kept (a property of
        the magnets; its widths may still go to 0), the filters starting from the fit's widths
        and start offsets. Not called while the play is used."""
        f, O, n = self.filter, torch.stack(self.O), len(self.X)
        if n <= holdout + 1:
            return
        w = torch.ones(n, dtype=O.dtype) if weights is None else weights.clone()
        w = w * f.forget ** torch.arange(n - 1, -1, -1, dtype=O.dtype)
        w[-holdout:] = 0.0
        keep = w > 1e-6
        if int(keep.sum()) < holdout:  # too few readings (e.g. just after a step): no change
            return
        ps = float(self.settings.prior_sd)

        def fit(rows: torch.Tensor) -> torch.Tensor:
            return fit_unknowns(f.model, rows[keep], O[keep], f.center, f.half_width,
                                obs_sd=self.obs_sd, prior_sd=ps, u0=f.u, max_iter=5,
                                weights=w[keep])[0]  # fmt: skip

        u_on = fit(self._rows(n, True))
        rows_on = self._rows_at(n, u_on)
        u_on = fit(rows_on)
        cost = []
        for rows, u in ((rows_on, u_on), (self._rows(n, False), None)):
            u = fit(rows) if u is None else u
            with torch.no_grad():
                pred = f.model(rows[-holdout:], f.center + f.half_width * u)
            cost.append(float(((O[-holdout:] - pred) / self.obs_sd).square().sum()))
        gain = cost[1] - cost[0]
        if gain > max(PLAY_EVIDENCE * 2 * self.dim, PLAY_EXPLAINS * cost[1]):
            self._play_on = True
            k = slice(-2 * self.dim, None)
            for u in f.U:
                u[k] = u_on[k]
            self._refresh_play()

    # -- the fit and the check ---------------------------------------------------------------

    def _refit_start(self, rounds: int = 3) -> None:
        r"""The filter's start with play: ``rounds`` batch fits of the unknowns, offsets and play
        to every reading so far (the play path refreshed at the widths of the fit before: the
        clip events settle); if the play is used (:meth:`_choose_play`) the filter starts from
        the last fit and its information, else from the state it was given (the play unused)."""
        f, O, n = self.filter, torch.stack(self.O), len(self.X)
        ps = float(self.settings.prior_sd)
        given = ([u.clone() for u in f.U], [L.clone() for L in f.L], [e.clone() for e in f.eta])
        u = f.u
        for _ in range(rounds):
            self._refresh_play()
            rows = self._rows(n, on=True)
            u, _ = fit_unknowns(f.model, rows, O, f.center, f.half_width, obs_sd=self.obs_sd,
                                prior_sd=ps, u0=u, max_iter=FIT_ITER)  # fmt: skip
            H = information(f.model, rows, f.center, f.half_width, u, obs_sd=self.obs_sd,
                            prior_sd=ps)  # fmt: skip
            f.U = [u.clone() for _ in f.forgets]
            f.L = [H - f.H0 for _ in f.forgets]
            f.eta = [H @ u for _ in f.forgets]
        self._choose_play()
        if not self._play_on:
            f.U, f.L, f.eta = given
        self.u = f.u[: self.center.numel()].clone()
        self._refresh_play()

    def _setpoint_for_fields(self, y: torch.Tensor) -> torch.Tensor:
        """The setpoint (``d``, within the bounds) that makes the acting fields ``y`` from the
        present state (:func:`~pigp_torch.optimizers.play.setpoint_for`; a field within
        ``PLAY_TOL`` of the present one is the present one). Only while the play is used."""
        H, w = self._play[0], self._play[3]
        lo, hi = self.bounds
        same = (y - self.X[-1] - H[-1]).abs() <= PLAY_TOL * (hi - lo)
        x = setpoint_for(torch.where(same, self.X[-1] + H[-1], y), self.X[-1], H[-1], w)
        return torch.minimum(torch.maximum(x, lo), hi)

    def _hold_small_moves(self, y: torch.Tensor) -> torch.Tensor:
        r"""The acting fields ``y`` asked, with the knobs asked to move by less than their play
        held where they are when the model predicts the goal within ``PLAY_HOLD`` noise sd of
        the ask's (a small move back costs a pass through the play, and a play known only
        approximately makes it inexact)."""
        H, w = self._play[0], self._play[3]
        now = self.X[-1] + H[-1]
        small = (y - now).abs() < w
        if not bool(small.any()):
            return y
        hold = torch.where(small, now, y)
        with torch.no_grad():
            g = self.goal_at(torch.stack([y, hold]), self.theta.detach())
        return hold if bool(g[1] <= g[0] + PLAY_HOLD * self.obs_sd) else y

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
        if self._play_half is not None:
            w = self.play_width if self.filter is not None else torch.zeros(self.dim, dtype=DTYPE)
            knobs = list(mm.knob_names) if mm is not None else [f"x{i}" for i in range(self.dim)]
            knob_units = list(mm.knob_units) if mm is not None else [""] * self.dim
            for n, v, u in zip(knobs, w, knob_units, strict=True):
                out[f"{n}_play"] = (float(v), u)
        return out
