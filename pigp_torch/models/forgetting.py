r"""A memory of the readings learned from the data: exponential forgetting and step detection.

A machine that drifts makes old readings wrong by an amount that grows with their age. Modelling
that as extra noise, reading :math:`i` (taken at reading count :math:`t_i`; time is the count of
readings) enters the fit at time :math:`t` with variance

.. math:: \sigma_i^2(t) = \sigma_n^2\, e^{(t - t_i)/\tau}, \qquad w_i = e^{-(t - t_i)/\tau},

so a Gaussian fit with these variances is the fit weighted by :math:`w_i` (the weighted
posterior). :math:`\tau` (readings) is the memory: :math:`\tau = \infty` keeps every reading
(a static machine), a small :math:`\tau` follows a fast drift.

:math:`\tau` is chosen from a grid by the *predictive likelihood* of recent readings: every
``every`` readings (from ``start`` readings on) the model is fitted with each :math:`\tau` to the
readings before the last ``block`` ones and scored by the Gaussian log density of those
``block`` readings under its prediction (mean, latent variance plus :math:`\sigma_n^2`); the
scores add up over checks with the factor ``discount`` per check,
:math:`S_\tau \leftarrow \gamma S_\tau + \ell_\tau`. A finite :math:`\tau` replaces
:math:`\infty` only when it leads by more than ``margin`` nats, so a static machine keeps
:math:`\tau = \infty` (and every fit equal to the one without this memory).

A height that changes (a ring's loss rate falls with its decaying current: the Touschek part
with the bunch current squared) makes old readings wrong everywhere by a factor, which a memory
short enough to follow it pays for with a large :math:`\sigma` everywhere. So the height is
tracked by a log-height slope :math:`s` (per reading) chosen with :math:`\tau`: the fit sees
each remembered reading's part above the background :math:`b` brought to the latest reading,
:math:`b + (y_i - b)\,e^{s (t - t_i)}`, and each check scores every pair :math:`(\tau, s)` of
the two grids (the prediction of a scored reading carried forward by the same factor); the
pair :math:`(\infty, 0)` keeps its place unless another leads by ``margin``. The centre then
keeps the longer memory its own motion allows.

Step detection: each new reading's standardized innovation against the current fit,
:math:`z = (y - \mu(\mathbf x)) / \sqrt{\sigma^2(\mathbf x) + \sigma_n^2}`, about
:math:`\mathcal N(0, 1)` while the machine is the fitted one, feeds a CUSUM of its square,
:math:`S \leftarrow \max(0, S + z^2 - 1 - k)` (a moved optimum raises some readings and
lowers others around the incumbent, so the squares, not the signs, show it); when :math:`S >
h` the readings before the excursion began are dropped (the memory restarts there) and a
notice is made (``kind = "drift_step"``).
"""

from __future__ import annotations

import copy
import math

import torch

from pigp_torch._utils import DTYPE

#: The memories :math:`\tau` (readings) compared by default: none, then 400 down to 25.
TAUS = (math.inf, 400.0, 200.0, 100.0, 50.0, 25.0)

#: The log-height slopes :math:`s` (per reading) compared by default: none, then falls of
#: 0.05, 0.1 and 0.2 % a reading (a height that falls to 78, 61 or 37 % over 500 readings; a
#: SPEAR3 current decaying by 10-30 % over a run makes the Touschek part fall by 0.04-0.17 %).
SLOPES = (0.0, -5e-4, -1e-3, -2e-3)


class Forgetting:
    r"""The learned memory of :class:`~pigp_torch.models.physics_posterior.PhysicsFormPosterior`
    (see the module docstring).

    Args:
        taus: the memories compared (readings; ``inf`` first: no forgetting).
        start: readings before the first check and before step detection (default 60: the
            check needs a ``block`` to score and enough readings before it to fit).
        every: readings between checks (default 10).
        block: recent readings each check scores (default 20).
        discount: :math:`\gamma`, the weight of the previous checks' scores (default 0.7).
        margin: lead in nats a finite :math:`\tau` needs over :math:`\infty` (default 3).
        cusum_k, cusum_h: the CUSUM's allowance :math:`k` and threshold :math:`h` (squared
            standardized units; defaults 3 and 25: about two readings at :math:`|z| \approx 4.5`,
            or five at 3, in a row).
        floor: readings whose weight falls below it are left out (default 1e-4).
        slopes: the log-height slopes :math:`s` compared (per reading; ``0`` first: a height
            that does not change). With :math:`s \ne 0` the fit sees each remembered reading's
            part above the background :math:`b` brought to the latest reading,
            :math:`b + (y_i - b)\,e^{s (t - t_i)}` (:meth:`rescale`); each check scores every
            pair :math:`(\tau, s)` and the pair :math:`(\infty, 0)` keeps its place unless
            another leads by ``margin``. Default :data:`SLOPES`; ``(0,)``: the height is not
            tracked.
    """

    def __init__(
        self,
        taus=TAUS,
        *,
        start: int = 60,
        every: int = 10,
        block: int = 20,
        discount: float = 0.7,
        margin: float = 3.0,
        cusum_k: float = 3.0,
        cusum_h: float = 25.0,
        floor: float = 1e-4,
        slopes=SLOPES,
    ) -> None:
        self.taus = tuple(float(t) for t in taus)
        if not self.taus or self.taus[0] != math.inf or min(self.taus) <= 0:
            raise ValueError(f"taus must start with inf and be positive, got {taus}")
        if int(block) < 1 or int(every) < 1 or int(start) <= int(block):
            raise ValueError("every and block must be >= 1 and start > block")
        self.start, self.every, self.block = int(start), int(every), int(block)
        self.discount, self.margin = float(discount), float(margin)
        self.cusum_k, self.cusum_h, self.floor = float(cusum_k), float(cusum_h), float(floor)
        self.slopes = tuple(float(s) for s in slopes)
        if not self.slopes or self.slopes[0] != 0.0:
            raise ValueError(f"slopes must start with 0, got {slopes}")
        self.tau, self.slope = math.inf, 0.0
        self.origin = 0  # the first reading remembered (a detected step moves it)
        self.scores = dict.fromkeys(self._pairs(), 0.0)
        self._cusum = 0.0
        self._excursion = 0  # where the current CUSUM excursion began
        self._n = 0
        self.notices: list[dict] = []

    def weights(self, n: int, tau: float | None = None, end: int | None = None):
        r"""``(first, w)`` for readings ``0 .. end - 1`` (default ``n``): the fit uses readings
        ``first ..`` with weights ``w`` (a tensor, or ``None`` for all 1 when nothing is
        forgotten); ``tau`` defaults to the learned one."""
        tau = self.tau if tau is None else tau
        end = n if end is None else end
        if tau == math.inf:
            return self.origin, None
        first = max(self.origin, end - 1 - math.floor(-tau * math.log(self.floor)))
        age = (end - 1) - torch.arange(first, end, dtype=DTYPE)
        return first, torch.exp(-age / tau)

    def due(self, n: int) -> bool:
        """Whether a check of :math:`\\tau` runs at ``n`` readings."""
        return n - self.origin >= self.start and n % self.every == 0

    def _pairs(self) -> list[tuple[float, float]]:
        return [(tau, slope) for slope in self.slopes for tau in self.taus]

    def rescale(self, Y: torch.Tensor, background: float, slope=None):
        r"""Consecutive readings ``Y`` (``n``) brought to the time of the last one by the log-height
        slope (default the learned one): :math:`b + (y_i - b)\,e^{s\,(t_\mathrm{last} -
        t_i)}`; ``Y`` itself when the slope is 0."""
        slope = self.slope if slope is None else slope
        if slope == 0.0:
            return Y
        age = (len(Y) - 1) - torch.arange(len(Y), dtype=DTYPE)
        return background + (Y - background) * torch.exp(slope * age)

    def select(self, model, X: torch.Tensor, Y: torch.Tensor) -> float:
        r"""One check: score every pair :math:`(\tau, s)` on the last ``block`` readings of
        ``X``, ``Y`` (copies of ``model`` fitted to the readings before them, the prediction
        of reading :math:`t` scaled by :math:`e^{s (t - t_\mathrm{cut})}` above the
        background), update :attr:`tau` and :attr:`slope`; returns :attr:`tau`."""
        n, cut = len(Y), len(Y) - self.block
        b = float(model.f_inf if model.theta is None else model.background())
        ahead = torch.arange(1, self.block + 1, dtype=DTYPE)
        for tau, slope in self._pairs():
            first, w = self.weights(n, tau, end=cut)
            trial = copy.copy(model)
            trial.fit(X[first:cut], self.rescale(Y[first:cut], b, slope), weights=w)
            with torch.no_grad():
                mu, sd = trial.predict(X[cut:])
            if slope != 0.0:
                k = torch.exp(slope * ahead)
                mu, sd = b + (mu - b) * k, sd * k
            var = sd**2 + model.noise**2
            ll = -0.5 * (Y[cut:] - mu) ** 2 / var - 0.5 * torch.log(2 * math.pi * var)
            ll = float(ll.sum())
            self.scores[tau, slope] = self.discount * self.scores[tau, slope] + ll
        best = max(self.scores, key=self.scores.get)
        lead = self.scores[best] - self.scores[math.inf, 0.0]
        self.tau, self.slope = best if lead > self.margin else (math.inf, 0.0)
        return self.tau

    def observe(self, model, x: torch.Tensor, y: float) -> bool:
        """The CUSUM of the innovation of reading ``y`` at ``x`` against the fitted ``model``
        (before it is refitted); on a detection the memory restarts at the excursion's first
        reading and a notice is queued. Returns whether a step was detected."""
        self._n += 1
        n = self._n
        if model.theta is None or n - self.origin <= self.start:
            return False
        with torch.no_grad():
            mu, sd = model.predict(x.reshape(1, -1))
        z = float((y - mu[0]) / math.sqrt(float(sd[0]) ** 2 + model.noise**2))
        if self._cusum == 0.0:
            self._excursion = n - 1
        self._cusum = max(0.0, self._cusum + z**2 - 1.0 - self.cusum_k)
        if self._cusum <= self.cusum_h:
            return False
        self.origin, level = self._excursion, self._cusum
        self._cusum = 0.0
        self.scores = dict.fromkeys(self._pairs(), 0.0)
        self.notices.append(
            dict(
                kind="drift_step",
                message=f"step change detected at reading {n}: the squared standardized "
                f"innovations since reading {self.origin + 1} exceed their expectation by "
                f"{level:.1f} (CUSUM); readings before it forgotten",
                n=n,
                origin=self.origin,
            )
        )
        return True
