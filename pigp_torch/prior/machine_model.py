r"""A machine's differentiable model: knobs, observables, unknowns and the goal.

A :class:`MachineModel` is everything the physics-informed methods need to know about a machine
whose model is differentiable (a Cheetah segment, a pyAT ring, a page of plain torch):

* the **knobs** :math:`x \in \mathbb R^d` (names, ``2 x d`` bounds, units);
* the **observables** :math:`o \in \mathbb R^m` the machine reads at each setting (names, units);
* the **unknowns** :math:`\theta \in \mathbb R^P` the operator does not know (e.g. the incoming
  beam and misalignments of a linac, error seeds of a ring), with the ranges they are drawn from:
  centre :math:`c` and half width :math:`h` (:math:`\theta \in [c - h, c + h]`);
* ``observe(X, theta)``: ``N x d`` settings and ``P`` unknowns ``->`` ``N x m`` observables,
  differentiable in both (autograd);
* ``goal(O)``: ``N x m`` observables ``->`` ``N`` values to MINIMIZE (smooth where it matters:
  its gradient drives the search), and optionally ``residual(O)`` (``N x m -> N x r``) whose zero
  is the goal's optimum (e.g. observables minus a target), which lets a least-squares search find
  a reachable optimum in a few Gauss–Newton steps.

:class:`~pigp_torch.optimizers.model_fit.FittedModelOptimizer` fits the unknowns online and asks
the model's optimum (``FittedModelOptimizer.from_machine_model``); :func:`prior_from_machine_model`
makes the paper's prior (:class:`~pigp_torch.prior.PhysicsPrior`) from the same description, with
the ensemble of optima over draws of the unknowns (:func:`machine_optima`) and the physics form's
peak shape (:func:`machine_peak_shape`) where asked: one code path for every machine kind.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor

from pigp_torch._utils import DTYPE
from pigp_torch.prior.peak_shape import mean_shape, peak_shape_at


@dataclass
class MachineModel:
    r"""A machine's differentiable model (module docstring).

    Attributes:
        name: a short name of the machine (e.g. ``"ares-ea"``).
        knob_names, knob_units: ``d`` names and units of the knobs.
        bounds: ``2 x d`` knob limits (knob units).
        observable_names, observable_units: ``m`` names and units of the observables.
        unknown_names, unknown_units: ``P`` names and units of the unknowns.
        unknown_center, unknown_half_width: ``P`` centre and half width (> 0) of the unknowns'
            ranges (their units).
        observe: ``(N x d, P) -> N x m`` observables, differentiable.
        goal: ``N x m -> N`` values to minimize (units of the goal: :attr:`goal_unit`).
        residual: optional ``N x m -> N x r`` residuals, zero at the goal's optimum.
        goal_unit: the goal's unit (default the first observable's unit).
        goal_background: optional ``P -> float``, the goal far from the optimum
            :math:`g_\infty(\theta)` where the model knows it (a ring's loss-rate background);
            default ``None``: :func:`prior_from_machine_model` takes the largest goal it samples.
        beam: optional ``(N x m, P) -> N x m``, the numbers the goal is on from the observables
            and the unknowns, where an instrument's response is among the unknowns (a screen's
            resolution blurs the sizes read: the goal is on the beam, not on the reading);
            default ``None``: the observables are what the goal is on.

    Raises:
        ValueError: sizes that do not agree, non-positive half widths, bounds with lower >=
            upper, or names that are not unique.
    """

    name: str
    knob_names: Sequence[str]
    knob_units: Sequence[str]
    bounds: Tensor
    observable_names: Sequence[str]
    observable_units: Sequence[str]
    unknown_names: Sequence[str]
    unknown_units: Sequence[str]
    unknown_center: Tensor
    unknown_half_width: Tensor
    observe: Callable[[Tensor, Tensor], Tensor]
    goal: Callable[[Tensor], Tensor]
    residual: Callable[[Tensor], Tensor] | None = None
    goal_unit: str | None = None
    goal_background: Callable[[Tensor], float] | None = None
    beam: Callable[[Tensor, Tensor], Tensor] | None = None

    def __post_init__(self) -> None:
        self.knob_names = list(self.knob_names)
        self.knob_units = list(self.knob_units)
        self.observable_names = list(self.observable_names)
        self.observable_units = list(self.observable_units)
        self.unknown_names = list(self.unknown_names)
        self.unknown_units = list(self.unknown_units)
        d, m, P = len(self.knob_names), len(self.observable_names), len(self.unknown_names)
        for what, names in (
            ("knob", self.knob_names),
            ("observable", self.observable_names),
            ("unknown", self.unknown_names),
        ):
            if len(set(names)) != len(names) or not names:
                raise ValueError(f"{what} names must be unique and not empty, got {names}")
        if len(self.knob_units) != d or len(self.observable_units) != m:
            raise ValueError("need one unit per knob and per observable")
        if len(self.unknown_units) != P:
            raise ValueError("need one unit per unknown")
        self.bounds = torch.as_tensor(self.bounds, dtype=DTYPE)
        if self.bounds.shape != (2, d) or not bool((self.bounds[0] < self.bounds[1]).all()):
            raise ValueError(f"bounds must be 2 x {d} with lower < upper")
        self.unknown_center = torch.as_tensor(self.unknown_center, dtype=DTYPE).reshape(-1)
        self.unknown_half_width = torch.as_tensor(self.unknown_half_width, dtype=DTYPE).reshape(-1)
        if self.unknown_center.shape != (P,) or self.unknown_half_width.shape != (P,):
            raise ValueError(f"unknown_center and unknown_half_width must have {P} numbers")
        if not bool((self.unknown_half_width > 0).all()):
            raise ValueError("unknown_half_width must be > 0")
        if self.goal_unit is None:
            self.goal_unit = self.observable_units[0]

    @property
    def dim(self) -> int:
        """Number of knobs ``d``."""
        return len(self.knob_names)

    def __call__(self, X: Tensor, theta: Tensor) -> Tensor:
        """``observe(X, theta)``: ``N x m`` observables at ``N x d`` settings."""
        return self.observe(X, theta)

    def goal_at(self, X: Tensor, theta: Tensor) -> Tensor:
        """The goal of the model's observables at ``N x d`` settings (``N``; through
        :attr:`beam` where there is one)."""
        O = self.observe(X, theta)
        return self.goal(O if self.beam is None else self.beam(O, theta))

    def sample_unknowns(self, n: int, seed: int = 0) -> Tensor:
        r"""``n x P`` unknowns drawn uniformly from their ranges (seeded)."""
        gen = torch.Generator().manual_seed(int(seed))
        u = 2 * torch.rand(int(n), len(self.unknown_names), generator=gen, dtype=DTYPE) - 1
        return self.unknown_center + self.unknown_half_width * u


def prior_from_machine_model(
    model: MachineModel,
    theta: Tensor | None = None,
    *,
    noise: float,
    n_ensemble: int = 0,
    seed: int = 0,
    goal_background: float | None = None,
    n_starts: int = 16,
    n_samples: int = 1024,
    peak_shape: bool = False,
):
    r"""The paper's physics prior (:class:`~pigp_torch.prior.PhysicsPrior`) from a machine model.

    The objective is :math:`f(x) = -g(M(x, \theta))` (the goal, maximized), at the unknowns
    ``theta`` (default: the centre of their ranges), with background :math:`f_\infty =
    -g_\infty`; :func:`~pigp_torch.prior.prior_from_model` finds its optimum :math:`x_0` and the
    autograd Hessian of :math:`\log(f - f_\infty) = \log(g_\infty - g)` there, whose
    :math:`-H/2` is the kernel's precision.

    With ``n_ensemble > 0`` the optimum is also found for ``n_ensemble`` draws of the unknowns
    (uniform in their ranges, seeded) and their covariance about the mean of the draws (plus
    ``1e-9`` of each knob's range squared on the diagonal, so that it is positive definite)
    is the prior's ``center_cov``: where the optimum of a machine drawn from the ranges tends to
    lie. The provenance records the mean of the draws' optima (``ensemble_mean``, knob units).
    With ``peak_shape`` as well, the prior's ``peak_shape`` is the mean over the draws of the
    physics form's shape at each draw's optimum (:func:`machine_peak_shape`,
    :func:`~pigp_torch.prior.peak_shape.mean_shape`), which ``pigp-physics`` reads.

    Args:
        model: the machine model.
        theta: ``P`` unknowns of the model (default :attr:`MachineModel.unknown_center`).
        noise: the goal's measurement noise standard deviation (goal units).
        n_ensemble: draws of the unknowns for ``center_cov`` (default 0: none).
        seed: seed of the draws and of the searches' Sobol points.
        goal_background: :math:`g_\infty` (goal units); default the model's
            :attr:`MachineModel.goal_background` at ``theta``, else the largest goal over the
            searches' Sobol samples of the box (the goal far from the optimum).
        n_starts, n_samples: the optimum search's starts and samples
            (:func:`~pigp_torch.prior.prior_from_model`).
        peak_shape: with ``n_ensemble > 0``, also the ensemble's mean shape (default no).

    Returns:
        The :class:`~pigp_torch.prior.PhysicsPrior` (knob units).

    The paper's prior assumes a smooth peak. A goal with a kink at its optimum (an absolute
    value) gives the Hessian of its smoothed version, and an optimum that is a valley (fewer
    observables than knobs, a reachable target) gives a precision that is singular along the
    valley, which :func:`~pigp_torch.prior.prior_from_model` repairs with a warning.
    """
    from pigp_torch.prior.build import prior_from_model

    theta0 = model.unknown_center if theta is None else torch.as_tensor(theta, dtype=DTYPE)
    b = model.bounds
    if goal_background is None and model.goal_background is not None:
        goal_background = model.goal_background(theta0)
    if goal_background is None:
        goal_background = _largest_goal(model, theta0, seed, n_samples)
    g_inf = float(goal_background)

    def f(X: Tensor) -> Tensor:
        return -model.goal_at(X, theta0)

    provenance = {"machine_model": model.name, "goal_background": g_inf}
    fields = {}
    if int(n_ensemble) > 0:
        fields = _ensemble_fields(model, int(n_ensemble), seed, n_starts, peak_shape, g_inf)
        provenance |= fields.pop("provenance")
    prior = prior_from_model(
        f,
        b,
        f_inf=-g_inf,
        noise=float(noise),
        n_starts=n_starts,
        seed=int(seed),
        n_samples=int(n_samples),
        knob_names=model.knob_names,
        provenance=provenance,
    )
    return dataclasses.replace(prior, **fields) if fields else prior


def _largest_goal(model: MachineModel, theta: Tensor, seed: int, n_samples: int) -> float:
    """The largest finite goal over ``n_samples`` scrambled Sobol points of the knob box."""
    b = model.bounds
    sobol = torch.quasirandom.SobolEngine(model.dim, scramble=True, seed=int(seed))
    Z = sobol.draw(max(int(n_samples), 1), dtype=DTYPE)
    with torch.no_grad():
        g = model.goal_at(b[0] + (b[1] - b[0]) * Z, theta)
    return float(g[torch.isfinite(g)].max())


class MachineOptima(NamedTuple):
    """The optima of a machine model over draws of its unknowns (:func:`machine_optima`)."""

    #: ``n x P`` unknowns drawn (:meth:`MachineModel.sample_unknowns`)
    thetas: Tensor
    #: ``n x d`` knob settings of the goal's optima (knob units), one per draw
    centers: Tensor
    #: ``n x d x d`` peak shapes at the optima (:func:`machine_peak_shape`), or ``None``
    shapes: Tensor | None


def machine_optima(
    model: MachineModel,
    n: int,
    *,
    seed: int = 0,
    n_starts: int = 16,
    shapes: bool = False,
    goal_background: float | None = None,
) -> MachineOptima:
    r"""The ensemble of optima of a machine model: for each of ``n`` seeded draws
    :math:`\theta_k` of the unknowns (uniform in their ranges), the optimum of the goal in the
    knob box (multi-start L-BFGS-B, ``n_starts`` Sobol starts, seed ``seed + k``) and, with
    ``shapes``, the physics form's peak shape there (:func:`machine_peak_shape` at
    :math:`\theta_k`, background the model's :attr:`MachineModel.goal_background` of
    :math:`\theta_k`, else ``goal_background``).

    Raises:
        ValueError: ``shapes`` without a background (neither the model's nor
            ``goal_background``).
    """
    from pigp_torch.prior.optimum import find_optimum

    b = model.bounds
    thetas = model.sample_unknowns(n, seed=seed)
    centers, found = [], []
    for k, th in enumerate(thetas):
        x, _ = find_optimum(
            lambda X, th=th: -model.goal_at(X, th), b, n_starts=n_starts, seed=int(seed) + k
        )
        centers.append(x)
        if shapes:
            found.append(machine_peak_shape(model, x, th, goal_background=goal_background))
    return MachineOptima(thetas, torch.stack(centers), torch.stack(found) if shapes else None)


def machine_peak_shape(
    model: MachineModel,
    x: Tensor,
    theta: Tensor | None = None,
    *,
    goal_background: float | None = None,
) -> Tensor:
    r"""The physics form's peak shape :math:`B = \tfrac12 \nabla^2 (f - f_\infty)^{-2}` of the
    model's objective :math:`f = -\mathrm{goal}(M(x, \theta))` at ``x`` (``d``, knob units),
    with :math:`f_\infty = -g_\infty`: :func:`~pigp_torch.prior.peak_shape.peak_shape_at`, the
    code the ring's error ensemble uses too. ``theta`` defaults to the unknowns' centre,
    :math:`g_\infty` to the model's :attr:`MachineModel.goal_background` at ``theta``, else
    ``goal_background``. Returns ``d x d`` ((goal unit)\ :sup:`-2` per knob unit squared).

    Raises:
        ValueError: no background (neither the model's nor ``goal_background``).
    """
    theta = model.unknown_center if theta is None else torch.as_tensor(theta, dtype=DTYPE)
    if model.goal_background is not None:
        goal_background = model.goal_background(theta)
    if goal_background is None:
        raise ValueError(f"machine model {model.name!r} has no goal_background: give one")
    return peak_shape_at(lambda X: -model.goal_at(X, theta), -float(goal_background), x)


def _ensemble_fields(model, n: int, seed: int, n_starts: int, peak_shape: bool, g_inf: float):
    """``center_cov`` (and with ``peak_shape`` the mean ``peak_shape``) of :func:`machine_optima`
    for :func:`prior_from_machine_model`, with its ``provenance`` entries."""
    optima = machine_optima(model, n, seed=seed, n_starts=n_starts, shapes=peak_shape,
                            goal_background=g_inf)  # fmt: skip
    center_cov, mean = _center_cov(optima.centers, model.bounds)
    fields = {"center_cov": center_cov}
    if peak_shape:
        fields["peak_shape"] = mean_shape(optima.shapes)
    return fields | {"provenance": {"ensemble_mean": mean.tolist(), "n_ensemble": n}}


def _center_cov(A: Tensor, b: Tensor) -> tuple[Tensor, Tensor]:
    """``(center_cov, mean)`` of ``n x d`` optima: their covariance about their mean plus
    ``1e-9`` of each knob's range squared (``b``: ``2 x d`` bounds) on the diagonal."""
    mean = A.mean(0)
    dev = A - mean
    jitter = 1e-9 * (b[1] - b[0]).square()
    return dev.T @ dev / max(len(A) - 1, 1) + torch.diag(jitter), mean
