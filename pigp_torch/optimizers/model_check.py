r"""The fitted model with a prior check: a model-free fallback when the model stops explaining
the readings.

:class:`CheckedModelOptimizer` is :class:`~pigp_torch.optimizers.model_fit.FittedModelOptimizer`
plus, after each fit (once ``check_after`` readings are in), a test of whether the fitted model
explains the last :math:`k = \min(\text{check\_window}, n)` readings:

.. math:: \chi^2 = \sum_{j = n-k+1}^{n} \Big\| \frac{o_j - M(x_j, \hat\theta)}{s} \Big\|^2,
    \qquad p = P\big(\chi^2_{k m} \ge \chi^2\big),

the tail probability of a chi-square with :math:`k m` degrees of freedom (:math:`m` observables
per reading, :math:`s` the stated noise). Under the right model with Gaussian noise of standard
deviation :math:`s` the residuals of the fit are at most as large as the noise (the fit absorbs
some), so :math:`p` is rarely small. After ``check_patience`` consecutive checks with
:math:`p <` ``check_alpha`` the model is not trusted any more: a notice says so, and from then on
every ask comes from a model-free search on the scalar ``y`` told with each reading (default:
the project's Nelder–Mead from the best reading so far, an initial simplex of 2 % of each knob's
range: a local search from where the model got to; or ``fallback="bo"``: BayesOpt on an ML-II
GP given every reading). :meth:`best` is then the best reading.

**The noise is learned before the model is given up.** A screen's stated noise is rarely all of
the scatter of its readings (the incoming beam and the supplies jitter shot to shot), and a check
at the stated noise then fails on a right model. So with ``noise_probe`` > 0 the first failed
check never hands over by itself (it counts towards ``check_patience``): the next asks re-read
its last setting (up to ``noise_probe`` times; once when the repeat reads the same to the bit, a
deterministic machine, which is then handed over at the same reading as without the probe), and
the scatter of every reading about its setting's mean gives the noise (pooled over the
:math:`m` observables, :math:`\nu = m (n - K)` degrees of freedom, :math:`n` readings at
:math:`K` distinct settings):

.. math:: \hat s^2 = \frac{1}{\nu} \sum_j \| o_j - \bar o_{k(j)} \|^2, \qquad
    s_{check} = \max\Big(s,\ \hat s \sqrt{\nu / \chi^2_{\nu, 0.05}}\Big),

the check's noise the 95 % upper confidence limit of :math:`\hat s` (a scatter seen on a few
repeats can be small by chance). A real model mismatch still fails: its residuals do not shrink
when the same setting is read again. When :math:`\hat s > s` the fit's noise becomes
:math:`\hat s` and :meth:`best` the setting where the fitted model predicts the best goal
(``best_from="model"``: with noisy readings the best reading is the luckiest, not the best).

:meth:`recommend` is the setting the evidence supports: :meth:`best` while the model is trusted;
after the hand-over on a machine whose readings repeat exactly, the best reading; on a noisy one,
the visited setting with the best posterior mean of a GP on the readings near the best
(:func:`~pigp_torch.optimizers.estimate.posterior_best`).

Why Nelder–Mead by default: a model that stops explaining the readings has usually brought the
beam close to the target already, where a local search from the best reading keeps that gain;
a GP fitted to every reading restarts a global search (the comparison on a wrong ARES-EA
calibration is in docs/results.md).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import torch

from pigp_torch._utils import DTYPE
from pigp_torch.optimizers.base import AskTellOptimizer
from pigp_torch.optimizers.estimate import posterior_best
from pigp_torch.optimizers.model_fit import FittedModelOptimizer


def bo_fallback(bounds, X, Y, *, maximize: bool, seed: int) -> AskTellOptimizer:
    """BayesOpt on an ML-II GP, told every reading so far (module docstring)."""
    from pigp_torch.models.ml2 import ml2_gp
    from pigp_torch.optimizers.bayesopt import BayesOpt

    opt = BayesOpt(bounds, lambda X, Y: ml2_gp(X, Y, bounds=bounds), maximize=maximize, seed=seed)
    for x, y in zip(X, Y, strict=True):
        opt.tell(x, y)
    return opt


def nm_fallback(bounds, X, Y, *, maximize: bool, seed: int, size: float = 0.02) -> AskTellOptimizer:
    """Nelder–Mead from the best reading so far, initial simplex ``size`` of each knob's range
    (a local search around where the model got to)."""
    from pigp_torch.optimizers.nelder_mead import NelderMead

    opt = NelderMead(bounds, initial_simplex_size=size, maximize=maximize)
    ys = torch.tensor(Y, dtype=DTYPE)
    i = int(ys.argmax() if maximize else ys.argmin())
    opt.tell(X[i], Y[i])
    return opt


FALLBACKS = {"bo": bo_fallback, "nm": nm_fallback}


def chi2_check(
    model: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
    X: torch.Tensor,
    O: torch.Tensor,
    theta: torch.Tensor,
    obs_sd: float,
) -> tuple[float, int, float]:
    r"""``(chi2, dof, p)`` of readings ``O`` (``k x m``) at ``X`` (``k x d``) against the model at
    ``theta`` (module docstring); ``p`` is the chi-square tail probability."""
    from scipy.stats import chi2 as chi2_dist

    with torch.no_grad():
        r = (O - model(X, theta)) / obs_sd
    value = float(r.square().sum())
    dof = int(r.numel())
    if value != value:  # NaN: the model cannot even predict
        return float("inf"), dof, 0.0
    return value, dof, float(chi2_dist.sf(value, dof))


class CheckedModelOptimizer(FittedModelOptimizer):
    r"""A fitted model whose prior check falls back to a model-free search (module docstring).

    Args:
        bounds: ``2 x d`` knob bounds.
        check_window: readings of each check (default 10).
        check_alpha: a check fails when its tail probability is below (default 1e-6).
        check_patience: consecutive failed checks before the fallback (default 2).
        check_after: readings before the first check (default 5).
        fallback: ``"nm"`` (:func:`nm_fallback`, default), ``"bo"`` (:func:`bo_fallback`) or a
            callable ``(bounds, X, Y, maximize=, seed=) -> AskTellOptimizer`` given the readings
            so far (``X``: list of ``d`` settings, ``Y``: list of told values).
        fallback_options: more keyword arguments of the fallback (e.g. ``{"size": 0.1}``).
        noise_probe: repeat readings of the noise probe at the first failed check (default 2;
            0: none, the check at the stated noise; module docstring).
        options: :class:`FittedModelOptimizer` arguments.

    Attributes:
        checks: one ``{"at_told", "chi2", "dof", "p"}`` per check.
        fallback: ``None`` while the model is trusted, then the model-free optimizer.
        noise_sd: the learned noise :math:`\hat s` (observable units; ``None`` before any
            repeat reading); check_sd: the noise of the checks (:math:`s_{check}`).
    """

    name = "model-fit-checked"

    def __init__(
        self,
        bounds,
        *,
        check_window: int = 10,
        check_alpha: float = 1e-6,
        check_patience: int = 2,
        check_after: int = 5,
        fallback: str | Callable[..., AskTellOptimizer] = "nm",
        fallback_options: dict | None = None,
        noise_probe: int = 2,
        **options,
    ) -> None:
        super().__init__(bounds, **options)
        if not (check_window >= 1 and 0 < check_alpha < 1 and check_patience >= 1):
            raise ValueError("need check_window >= 1, 0 < check_alpha < 1, check_patience >= 1")
        if int(noise_probe) < 0:
            raise ValueError(f"noise_probe must be >= 0, got {noise_probe}")
        self.noise_probe = int(noise_probe)
        self.noise_sd: float | None = None
        self._stated = self.settings  # the settings with the stated noise
        self.check_sd = self.obs_sd
        self._probe: list = []  # [setting, repeats left] while the probe runs
        self._probed = False
        self.check_window = int(check_window)
        self.check_alpha = float(check_alpha)
        self.check_patience = int(check_patience)
        self.check_after = int(check_after)
        if isinstance(fallback, str):
            if fallback not in FALLBACKS:
                raise ValueError(f"unknown fallback {fallback!r}; known: {sorted(FALLBACKS)}")
            fallback = FALLBACKS[fallback]
        self.fallback_factory = fallback
        self.fallback_options = dict(fallback_options or {})
        self.fallback: AskTellOptimizer | None = None
        self.checks: list[dict] = []
        self._failed = 0

    def tell(self, x, y: float, observables=None) -> None:
        """Record and refit (:meth:`FittedModelOptimizer.tell`), then check the model; after the
        fallback the reading also goes to the model-free search."""
        super().tell(x, y, observables=observables)
        if self.fallback is not None:
            self.fallback.tell(self.X[-1], y)
            return
        if self.n_told < self.check_after:
            return
        if self._merged.counts and len(self._merged.x) < self.n_told:
            self._learn_noise()
        k = min(self.check_window, self.n_told)
        X, O = torch.stack(self.X[-k:]), torch.stack(self.O[-k:])
        chi2, dof, p = chi2_check(self.model, X, O, self.theta.detach(), self.check_sd)
        self.checks.append({"at_told": self.n_told, "chi2": chi2, "dof": dof, "p": p})
        failed = p < self.check_alpha
        self._failed = self._failed + 1 if failed else 0
        if failed and not self._probed and self.noise_probe > 0:
            # The first failed check: the next asks read the same setting again.
            self._probed, self._probe = True, [self.X[-1].clone(), self.noise_probe]
            return
        if self._failed >= self.check_patience:
            self._fall_back(chi2, dof, p, k)

    def _learn_noise(self) -> None:
        """The noise from the scatter of the repeat readings (module docstring); the fit's
        noise and :meth:`best`'s choice follow when it exceeds the stated noise."""
        from scipy.stats import chi2 as chi2_dist

        nu = (self.n_told - len(self._merged.x)) * self.O[-1].numel()
        s_hat = math.sqrt(self._merged.scatter(self.O, 1.0) / nu)
        self.noise_sd = s_hat
        if self._probe and s_hat == 0.0:
            self._probe = []  # the repeat read the same to the bit: a deterministic machine
        upper = s_hat * math.sqrt(nu / chi2_dist.ppf(0.05, nu))
        stated = self._stated.obs_sd
        self.check_sd = max(stated, upper)
        noisy = s_hat > stated
        self.settings = (
            dataclasses.replace(self._stated, obs_sd=s_hat, best_from="model")
            if noisy
            else self._stated
        )

    def _fall_back(self, chi2: float, dof: int, p: float, k: int) -> None:
        self.fallback = self.fallback_factory(
            self.bounds,
            self.X,
            self.Y,
            maximize=self.maximize,
            seed=self.seed,
            **self.fallback_options,
        )
        self.notify(
            "prior-check",
            f"the fitted model does not explain the readings (chi2 {chi2:.1f} for {dof} numbers "
            f"over the last {k} readings, p = {p:.1e} < {self.check_alpha:g}, "
            f"{self.check_patience} checks in a row): a model-free search asks from now on",
            chi2=chi2,
            dof=dof,
            p=p,
        )

    def ask(self) -> torch.Tensor:
        """The fitted model's optimum, or the fallback's ask once it has taken over."""
        if self.fallback is not None:
            return self.fallback.ask().to(DTYPE)
        if self._probe and self._probe[1] > 0:
            self._probe[1] -= 1
            return self._probe[0].clone()
        return super().ask()

    def recommend(self) -> torch.Tensor:
        """The setting the evidence supports (``d``; module docstring): :meth:`best`'s while the
        model is trusted or the readings repeat exactly; after the hand-over on noisy readings,
        the visited setting with the best GP posterior mean
        (:func:`~pigp_torch.optimizers.estimate.posterior_best`)."""
        noisy = self.best_from == "model" or bool(self.noise_sd)
        if self.fallback is None or not noisy:
            return self.best()[0]
        i = posterior_best(torch.stack(self.X), torch.tensor(self.Y, dtype=DTYPE), self.bounds,
                           maximize=self.maximize)  # fmt: skip
        return self.X[i].clone()

    def best(self) -> tuple[torch.Tensor, float]:
        """As :meth:`FittedModelOptimizer.best`; the best reading once the fallback has taken
        over (the model that would choose otherwise is not trusted)."""
        if self.fallback is not None:
            return AskTellOptimizer.best(self)
        return super().best()
