r"""The acquisition part of the Bayesian-optimization core, written once against the posterior.

Each acquisition reads the :class:`~pigp_torch.models.posterior.Prediction` of any
:class:`~pigp_torch.models.posterior.Posterior` (internal, maximized sign; mean :math:`\mu`,
standard deviation :math:`\sigma`, best observed value :math:`y^*`,
:math:`z = (\mu - y^*)/\sigma`, :math:`h(z) = \varphi(z) + z\Phi(z)`) and returns its value with
derivatives up to the order the search asks for, using only those of :math:`\mu` and
:math:`\sigma`:

* :class:`UCB`: :math:`\mu + \sqrt\beta\,\sigma` (BoTorch convention; :math:`\beta = 4` is the
  authors' :math:`\mu + 2\sigma`); :math:`\nabla = \nabla\mu + \sqrt\beta\nabla\sigma`, same for
  the Hessian;
* :class:`EI`: :math:`\sigma h(z)`; :math:`\nabla = \Phi\nabla\mu + \varphi\nabla\sigma`,
  :math:`\nabla^2 = \Phi\nabla^2\mu + \varphi\nabla^2\sigma + (\varphi/\sigma)\mathbf w
  \mathbf w^\top`, :math:`\mathbf w = \nabla\mu - z\nabla\sigma`;
* :class:`LogEI`: :math:`\log\sigma + \log h(z)`; with :math:`r = \Phi(z)/h(z)` and
  :math:`\nabla z = \mathbf w/\sigma`: :math:`\nabla = \nabla\sigma/\sigma + r\nabla z`,
  :math:`\nabla^2 = \nabla^2\sigma/\sigma - \nabla\sigma\nabla\sigma^\top/\sigma^2 +
  r\nabla^2 z + (1 - zr - r^2)\nabla z\nabla z^\top`, :math:`\nabla^2 z = (\nabla^2\mu -
  z\nabla^2\sigma)/\sigma - (\nabla\sigma\nabla z^\top + \nabla z\nabla\sigma^\top)/\sigma`;
* :class:`CentreInformation`: what one more reading tells about the fitted centre of the
  physics form (a posterior with ``centre_information``);
* :class:`CorrelatedCentreInformation`: the same with the readings' errors correlated by the
  residual GP (the exact update);
* :class:`ExpectedCentreInformation`: that, averaged over the posterior of the form's parameters;
* :class:`Alternating`: one acquisition every ``every``-th ask, another otherwise;
* :class:`Schedule`: the acquisition of each ask from a written schedule of letters;
* :class:`BoTorchAcquisition`: a BoTorch ``AcquisitionFunction`` built on the posterior's BoTorch
  ``model`` (for :class:`~pigp_torch.optimizers.bo.search.OptimizeAcqf`).

The contract tests check :class:`UCB`, :class:`EI` and :class:`LogEI` on every posterior
against BoTorch's analytic acquisitions.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import scipy.special

_SQRT_HALF_PI = math.sqrt(math.pi / 2)
_LOG_SQRT_2PI = 0.5 * math.log(2 * math.pi)


def _log_h(z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    r""":math:`\log h(z)` and :math:`\Phi(z) / h(z)` for :math:`h(z) = \varphi(z) + z\Phi(z)`.

    :math:`h` is the expected improvement of a unit Gaussian; :math:`h' = \Phi`. For
    :math:`z \le -1` both are computed from the Mills ratio :math:`R(t) = \Phi(-t)/\varphi(t) =
    \sqrt{\pi/2}\,\mathrm{erfcx}(t/\sqrt2)`, :math:`h(-t) = \varphi(t)(1 - tR(t))`, and for
    :math:`t > 40` from the asymptotic series :math:`1 - tR(t) = t^{-2} - 3t^{-4} + 15t^{-6} -
    105t^{-8} + 945t^{-10}` (relative error < 1e-12), so LogEI stays finite far from the data.
    """
    z = np.asarray(z, dtype=np.float64)
    log_h = np.empty_like(z)
    ratio = np.empty_like(z)
    hi = z > -1.0
    zh = z[hi]
    h = np.exp(-0.5 * zh**2 - _LOG_SQRT_2PI) + zh * scipy.special.ndtr(zh)
    log_h[hi] = np.log(h)
    ratio[hi] = scipy.special.ndtr(zh) / h
    t = -z[~hi]
    mills = _SQRT_HALF_PI * scipy.special.erfcx(t / math.sqrt(2))
    inv2 = 1.0 / t**2
    series = inv2 * (1 - inv2 * (3 - inv2 * (15 - inv2 * (105 - 945 * inv2))))
    one_minus = np.where(t > 40.0, series, 1.0 - t * mills)
    log_h[~hi] = -0.5 * t**2 - _LOG_SQRT_2PI + np.log(one_minus)
    ratio[~hi] = mills / one_minus  # Phi(-t)/h(-t) = R(t) phi(t) / (phi(t) (1 - tR))
    return log_h, ratio


class _Analytic:
    """Shared :meth:`bind`: the acquisition as ``fun(X: N x d, order)`` on a posterior."""

    name = "analytic"
    #: Highest derivative order the acquisition gives (the posterior may give fewer).
    max_order = 2

    def bind(self, posterior, best_f: float, step: int) -> Callable:
        """``fun(X, order)``: values (``order=0``) or ``(values, grads[, hessians])``; its
        ``max_order`` attribute is the highest order it gives."""
        best = float(best_f)

        def fun(X, order=0):
            return self.evaluate(posterior, X, order, best)

        fun.max_order = min(self.max_order, posterior.max_order)
        return fun

    def evaluate(self, posterior, X: np.ndarray, order: int, best_f: float):
        raise NotImplementedError


def _standardized(posterior, X: np.ndarray, order: int, best_f: float):
    r"""The prediction at ``X``, its :math:`\sigma` and :math:`z = (\mu - y^*)/\sigma`."""
    p = posterior.predict(X, order)
    return p, p.std, (p.mean - best_f) / p.std


class UCB(_Analytic):
    r""":math:`\mu + \sqrt\beta\,\sigma` (module docstring).

    Args:
        beta: :math:`\beta \ge 0`, finite.
    """

    name = "ucb"

    def __init__(self, beta: float = 4.0) -> None:
        if not (float(beta) >= 0.0 and float(beta) < float("inf")):
            raise ValueError(f"beta must be finite and >= 0, got {beta}")
        self.beta = float(beta)

    def evaluate(self, posterior, X: np.ndarray, order: int, best_f: float):
        p = posterior.predict(X, order)
        sb = math.sqrt(self.beta)
        value = p.mean + sb * p.std
        if order == 0:
            return value
        if order == 1:
            return value, p.dmean + sb * p.dstd
        return value, p.dmean + sb * p.dstd, p.hmean + sb * p.hstd


class EI(_Analytic):
    r"""Expected improvement :math:`\sigma h(z)` over the best reading (module docstring)."""

    name = "ei"

    def evaluate(self, posterior, X: np.ndarray, order: int, best_f: float):
        p, sigma, z = _standardized(posterior, X, order, best_f)
        pdf = np.exp(-0.5 * z**2 - _LOG_SQRT_2PI)
        cdf = scipy.special.ndtr(z)
        value = sigma * (pdf + z * cdf)
        if order == 0:
            return value
        dmu, dsig = p.dmean, p.dstd
        grad = cdf[:, None] * dmu + pdf[:, None] * dsig
        if order == 1:
            return value, grad
        w = dmu - z[:, None] * dsig
        hess = (
            cdf[:, None, None] * p.hmean
            + pdf[:, None, None] * p.hstd
            + np.einsum("N,Ni,Nj->Nij", pdf / sigma, w, w)
        )
        return value, grad, hess


class LogEI(_Analytic):
    r""":math:`\log(\sigma h(z))`, finite far from the data (module docstring, :func:`_log_h`)."""

    name = "logei"

    def evaluate(self, posterior, X: np.ndarray, order: int, best_f: float):
        p, sigma, z = _standardized(posterior, X, order, best_f)
        log_h, ratio = _log_h(z)
        value = np.log(sigma) + log_h
        if order == 0:
            return value
        dmu, dsig = p.dmean, p.dstd
        dz = (dmu - z[:, None] * dsig) / sigma[:, None]
        grad = dsig / sigma[:, None] + ratio[:, None] * dz
        if order == 1:
            return value, grad
        hmu, hsig = p.hmean, p.hstd
        s3 = sigma[:, None, None]
        outer = np.einsum("Ni,Nj->Nij", dsig, dz)
        hz = (hmu - z[:, None, None] * hsig) / s3 - (outer + outer.transpose(0, 2, 1)) / s3
        hess = (
            hsig / s3
            - np.einsum("Ni,Nj->Nij", dsig, dsig) / s3**2
            + ratio[:, None, None] * hz
            + np.einsum("N,Ni,Nj->Nij", 1.0 - z * ratio - ratio**2, dz, dz)
        )
        return value, grad, hess


class CentreInformation(_Analytic):
    r"""The reduction of :math:`\mathrm{tr}(B\,C_\mu)` by one more reading, :math:`C_\mu` the
    Laplace covariance of the physics form's fitted centre
    (:meth:`~pigp_torch.models.physics_posterior.PhysicsFormPosterior.centre_information`);
    orders 0 and 1."""

    name = "centre_information"
    max_order = 1

    def evaluate(self, posterior, X: np.ndarray, order: int, best_f: float):
        return posterior.centre_information(X, order)


class CorrelatedCentreInformation(CentreInformation):
    r""":class:`CentreInformation` with the readings' errors correlated by the residual GP:
    the exact update of the Laplace precision by one more reading, :math:`\mathbf u\mathbf
    u^\top/s^2` with :math:`\mathbf u = \mathbf j - G^\top\Sigma^{-1}\mathbf k` (a
    posterior with ``correlated_centre_information``); orders 0 and 1. A reading next to told
    ones is worth less than the independent formula says."""

    name = "correlated_centre_information"

    def evaluate(self, posterior, X: np.ndarray, order: int, best_f: float):
        return posterior.correlated_centre_information(X, order)


class ExpectedCentreInformation(CentreInformation):
    r""":class:`CorrelatedCentreInformation` averaged over the posterior of the form's
    parameters (``2 rank + 1`` sigma points of the Laplace posterior along the centre's
    costliest directions; a posterior with ``expected_centre_information``), not at the point
    estimate; orders 0 and 1.

    Args:
        rank: directions of the sigma points (``>= 0``; 0 is the point estimate; default 3).
        kappa: weight of the point estimate, :math:`\kappa/(r + \kappa)` (``> 0``; default 1).
    """

    name = "expected_centre_information"

    def __init__(self, rank: int = 3, kappa: float = 1.0) -> None:
        if int(rank) < 0 or not (math.isfinite(float(kappa)) and float(kappa) > 0):
            raise ValueError(f"rank must be >= 0 and kappa > 0, got {rank} and {kappa}")
        self.rank, self.kappa = int(rank), float(kappa)

    def evaluate(self, posterior, X: np.ndarray, order: int, best_f: float):
        return posterior.expected_centre_information(X, order, self.rank, self.kappa)


class Alternating:
    """``other`` at every ``every``-th ask (``step % every == 0``, ``every > 0``), ``main``
    otherwise; :attr:`last` names the one bound last.

    Args:
        main: the usual acquisition.
        other: the occasional one.
        every: period in asks (``0``: never ``other``).
    """

    def __init__(self, main, other, every: int) -> None:
        if int(every) < 0:
            raise ValueError(f"info_every must be >= 0, got {every}")
        self.main, self.other, self.every = main, other, int(every)
        self.last = None

    def bind(self, posterior, best_f: float, step: int):
        chosen = self.other if self.every > 0 and step % self.every == 0 else self.main
        self.last = chosen
        return chosen.bind(posterior, best_f, step)


class WhileDrifting:
    """``steady`` while the posterior finds the machine static, ``drifting`` while it follows a
    drift (its ``drifting`` is true: a finite learned memory or a detected step,
    :class:`~pigp_torch.models.physics_posterior.PhysicsFormPosterior`); :attr:`last` is the
    acquisition the chosen one bound last (its own ``last`` when it has one).

    Args:
        steady: the acquisition of a static machine.
        drifting: the acquisition while tracking.
    """

    def __init__(self, steady, drifting) -> None:
        self.steady, self.drifting = steady, drifting
        self.last = None

    def bind(self, posterior, best_f: float, step: int):
        chosen = self.drifting if posterior.drifting else self.steady
        bound = chosen.bind(posterior, best_f, step)
        self.last = chosen.last if isinstance(chosen, (Alternating, Schedule)) else chosen
        return bound


class Schedule:
    """The acquisition of each ask read from a schedule of letters.

    ``schedule`` is a ``/``-separated list of segments ``PATTERN@COUNT``, the last one without a
    count: the first segment's pattern, repeated, chooses the first ``COUNT`` asks, the next
    segment the following ones, and the last pattern repeats for the rest of the run. Ask ``k``
    (``k = step``, 1 for the first ask after the start point) of a segment that began at ask
    ``s`` uses the letter ``PATTERN[(k - s) % len(PATTERN)]``. E.g. ``"uui"`` is
    :class:`Alternating` with ``every = 3`` (asks 3, 6, ... the second acquisition), and
    ``"i@4/mi"``: four asks of ``i``, then ``m`` and ``i`` alternately.

    Args:
        acquisitions: the acquisition of each letter.
        schedule: the schedule text (letters of ``acquisitions`` only).

    Raises:
        ValueError: an empty pattern, a letter without an acquisition, a count below 1, or a
            count on the last segment.
    """

    def __init__(self, acquisitions: dict, schedule: str) -> None:
        self.acquisitions = dict(acquisitions)
        self.schedule = str(schedule)
        self.segments: list[tuple[str, int | None]] = []
        parts = self.schedule.split("/")
        for i, part in enumerate(parts):
            pattern, at, count = part.partition("@")
            last = i == len(parts) - 1
            if not pattern or any(c not in self.acquisitions for c in pattern):
                raise ValueError(
                    f"schedule {schedule!r}: each pattern needs letters of "
                    f"{sorted(self.acquisitions)}, got {pattern!r}"
                )
            if last and at:
                raise ValueError(f"schedule {schedule!r}: the last segment repeats, no count")
            if not last and not (count.isdigit() and int(count) >= 1):
                raise ValueError(f"schedule {schedule!r}: segment {part!r} needs a count >= 1")
            self.segments.append((pattern, None if last else int(count)))
        self.last = None

    def letter(self, step: int) -> str:
        """The letter of ask ``step`` (1 for the first ask)."""
        k = int(step) - 1
        for pattern, count in self.segments:
            if count is None or k < count:
                return pattern[k % len(pattern)]
            k -= count
        raise AssertionError("unreachable: the last segment has no count")

    def bind(self, posterior, best_f: float, step: int):
        self.last = self.acquisitions[self.letter(step)]
        return self.last.bind(posterior, best_f, step)


class BoTorchAcquisition:
    """A BoTorch ``AcquisitionFunction`` on the posterior's BoTorch ``model``.

    Args:
        make: ``(model, best_f) -> AcquisitionFunction``, e.g. :func:`botorch_analytic`.
    """

    def __init__(self, make: Callable) -> None:
        self.make = make

    def bind(self, posterior, best_f, step: int):
        return self.make(posterior.model, best_f)


#: Acquisition names of the recipes.
ACQUISITIONS = ("ucb", "ei", "logei")


def check_acquisition(name: str) -> str:
    """``name`` lower-cased, one of :data:`ACQUISITIONS`."""
    name = str(name).lower()
    if name not in ACQUISITIONS:
        raise ValueError(f"acquisition must be one of {ACQUISITIONS}, got {name!r}")
    return name


def analytic(name: str, beta: float = 4.0) -> _Analytic:
    """The core's own acquisition of ``name`` (:data:`ACQUISITIONS`)."""
    name = check_acquisition(name)
    return UCB(beta) if name == "ucb" else EI() if name == "ei" else LogEI()


def botorch_analytic(name: str, beta: float = 4.0) -> BoTorchAcquisition:
    """BoTorch's ``UpperConfidenceBound`` / ``ExpectedImprovement`` / ``LogExpectedImprovement``
    of ``name`` (``best_f``: the best reading, internal sign)."""
    from botorch.acquisition import (
        ExpectedImprovement,
        LogExpectedImprovement,
        UpperConfidenceBound,
    )

    name = check_acquisition(name)
    UCB(beta)  # validates beta
    if name == "ucb":
        return BoTorchAcquisition(lambda model, best_f: UpperConfidenceBound(model, beta=beta))
    cls = ExpectedImprovement if name == "ei" else LogExpectedImprovement
    return BoTorchAcquisition(lambda model, best_f: cls(model, best_f=best_f))
