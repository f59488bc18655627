r"""Drift families of simulated rings (SPEAR3 by default; docs/drift_families.md).

A machine of a family is the benchmark's machine ``seed`` (its own errors and loss-rate map,
:func:`~pigp_torch.bench.machines.benchmark_ring`) seen through its machine model
(:func:`~.model.ring_machine_model`: the fast linear model, differentiable) with unknowns that
change with the reading count :math:`t`:

.. math:: \theta(t) = \bigl(\delta(t),\ d(t),\ e(t)\bigr),\qquad
    f_t(x) = f_\infty (1 + d(t)) + (1 + e(t))\,\bigl(F(x + \delta(t)) - f_\infty\bigr),

with :math:`F` the machine's own loss rate (mA/min) and :math:`\delta` the coupling change as the
knob setting that would cause it (so the optimum moves by :math:`-\delta(t)`). :data:`DURATION`
= 500 readings is "a run". Components (drawn from ``seed`` with :data:`DRIFT_SEED`):

* ``coupling`` (an insertion device's gap moving): :math:`\delta(t) = (t / T)\,\Delta_c`, a
  direction drawn uniformly on the sphere of knob space, its length set so that at the end of a
  run the start's optimum keeps a fraction :data:`GAIN_LEFT` of the gain (bisection on the
  length with the model). Only the part of the coupling change the knobs can compensate is
  modelled (a skew error at the ID straight projects onto it); vertical dispersion is not.
* ``scale`` (the coupling errors' scale drifting): :math:`\delta(t) = -a\,(t/T)\,x^*_0`, the
  errors' compensable part :math:`-x^*_0` grown by :math:`a` in :data:`SCALE_GROWTH` over a run.
* ``current`` (the loss rate's scale changing with beam current, decay between fills): the
  current :math:`I(t)/I_0 = 1 - r\,t/T`, :math:`r` in :data:`CURRENT_DROP`; gas scattering
  :math:`\propto I`: :math:`1 + d = I/I_0`; Touschek :math:`\propto I^2`:
  :math:`1 + e = (I/I_0)^2`.
* ``step``: at reading :data:`STEP_AT` the coupling jumps by :math:`\Delta_s` (drawn as
  :math:`\Delta_c`, the start's optimum keeping :data:`GAIN_LEFT` of the gain right after).

Scoring (:func:`gain_series`): the gain against the moving optimum
:math:`(f_t(x_t) - f_t(0)) / (f^*_t - f_t(0))`, :math:`f^*_t` from
:func:`~pigp_torch.machines.drift.optimum_track`.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch
from torch import Tensor

from pigp_torch._utils import DTYPE
from pigp_torch.machine.model_machine import ModelMachine
from pigp_torch.machines.drift import family_components, interpolate_track, optimum_track
from pigp_torch.machines.ring.model import ring_machine_model

DURATION: int = 500
GAIN_LEFT: tuple[float, float] = (0.4, 0.6)
SCALE_GROWTH: tuple[float, float] = (0.2, 0.4)
CURRENT_DROP: tuple[float, float] = (0.1, 0.3)
STEP_AT: int = 250
DRIFT_SEED: int = 58_000

#: The families and their components (module docstring).
RING_FAMILIES: dict[str, frozenset[str]] = {
    "none": frozenset(),
    "id-gap": frozenset({"coupling"}),
    "coupling-scale": frozenset({"scale"}),
    "current": frozenset({"current"}),
    "coupling-step": frozenset({"step"}),
    "drift": frozenset({"coupling", "current"}),
    "drift-step": frozenset({"coupling", "current", "step"}),
}


def check_family(family: str) -> frozenset[str]:
    """The components of ``family`` (ValueError: an unknown one)."""
    return family_components(RING_FAMILIES, family, "ring")


def _gain_of(F: Callable[[Tensor], Tensor], x0: Tensor, f_star: float, f_zero: float):
    return lambda shift: (float(F((x0 + shift)[None])[0]) - f_zero) / (f_star - f_zero)


def coupling_shift(
    F: Callable[[Tensor], Tensor], x_star: Tensor, direction: Tensor, keep: float
) -> Tensor:
    r"""The shift :math:`\Delta = s\,\hat u` along ``direction`` at which the optimum ``x_star``
    of ``F`` keeps the fraction ``keep`` of the gain :math:`F(x^*) - F(0)`:
    :math:`F(x^* + \Delta) - F(0) = \text{keep}\,(F(x^*) - F(0))` (bisection on :math:`s`, 40
    halvings; control units)."""
    u = direction / direction.norm()
    f_zero = float(F(torch.zeros(1, len(u), dtype=DTYPE))[0])
    f_star = float(F(x_star[None])[0])
    gain = _gain_of(F, x_star, f_star, f_zero)
    hi = 1.0
    while gain(hi * u) > keep and hi < 1e3:
        hi *= 2
    lo = 0.0
    for _ in range(40):
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if gain(mid * u) > keep else (lo, mid)
    return (lo + hi) / 2 * u


class RingTheta:
    r"""The unknowns :math:`\theta(t)` of a family's machine (module docstring).

    Args:
        K: number of knobs; components: the family's components.
        coupling, step: ``K`` shifts :math:`\Delta_c, \Delta_s` (control units).
        scale_dir: ``K`` :math:`-a\,x^*_0`; current_drop: :math:`r`.
    """

    def __init__(self, K, components, coupling, step, scale_dir, current_drop) -> None:
        self.K, self.components = int(K), frozenset(components)
        self.coupling, self.step, self.scale_dir = coupling, step, scale_dir
        self.current_drop = float(current_drop)

    def current(self, t: int) -> float:
        r""":math:`I(t)/I_0` (1 without the ``current`` component)."""
        if "current" not in self.components:
            return 1.0
        return 1.0 - self.current_drop * t / DURATION

    def __call__(self, t: int) -> Tensor:
        """``K + 2`` unknowns at reading ``t``."""
        c, delta = self.components, torch.zeros(self.K, dtype=DTYPE)
        if "coupling" in c:
            delta = delta + self.coupling * (t / DURATION)
        if "scale" in c:
            delta = delta + self.scale_dir * (t / DURATION)
        if "step" in c and t >= STEP_AT:
            delta = delta + self.step
        i = self.current(t)
        return torch.cat([delta, torch.tensor([i - 1.0, i * i - 1.0], dtype=DTYPE)])


def draw_theta(sim, family: str, seed: int) -> RingTheta:
    """The :class:`RingTheta` of ``family`` for the ring ``sim`` with draw seed ``seed`` (all
    draws made always, in one order; the generator seeded with :data:`DRIFT_SEED` + ``seed``)."""
    c = check_family(family)
    gen = torch.Generator().manual_seed(DRIFT_SEED + int(seed))
    K = sim.dim
    u_c, u_s = (torch.randn(K, generator=gen, dtype=DTYPE) for _ in range(2))
    keep = GAIN_LEFT[0] + (GAIN_LEFT[1] - GAIN_LEFT[0]) * torch.rand(2, generator=gen)
    a = SCALE_GROWTH[0] + (SCALE_GROWTH[1] - SCALE_GROWTH[0]) * float(torch.rand(1, generator=gen))
    r = CURRENT_DROP[0] + (CURRENT_DROP[1] - CURRENT_DROP[0]) * float(torch.rand(1, generator=gen))
    zero = torch.zeros(K, dtype=DTYPE)
    x_star = sim.optimum()[0] if c & {"coupling", "step", "scale"} else zero
    F = sim.loss_rate
    coupling = coupling_shift(F, x_star, u_c, float(keep[0])) if "coupling" in c else zero
    step = coupling_shift(F, x_star, u_s, float(keep[1])) if "step" in c else zero
    return RingTheta(K, c, coupling, step, -a * x_star, r)


class RingDriftMachine(ModelMachine):
    r"""A ring whose unknowns follow :math:`\theta(t)`, read with noise on every observable
    (:class:`~pigp_torch.machine.model_machine.ModelMachine`, ``maximize=True``: ``read()`` is
    the loss rate in mA/min).

    Args:
        model: the machine's model (:func:`~.model.ring_machine_model` of the machine ring).
        theta: ``t -> θ(t)`` (:class:`RingTheta`).
        noise: each observable's noise sd (default 0.04, mA/min on the loss rate).
        seed: the noise's seed.

    Attributes:
        n_reads: readings taken; last_true_observables: ``3`` noise-free observables of the last
        reading.
    """

    def __init__(self, model, theta: RingTheta, *, noise: float = 0.04, seed: int = 0) -> None:
        super().__init__(model, theta(0), noise=noise, seed=seed, maximize=True,
                         x_init=torch.zeros(len(model.knob_names), dtype=DTYPE))  # fmt: skip
        self.theta_at = theta
        self.n_reads = 0
        self.last_true_observables: Tensor | None = None

    def loss_rate_at(self, X, t: int) -> Tensor:
        """Noise-free loss rate (mA/min) at ``N x K`` settings, reading ``t`` (differentiable)."""
        return self.model.observe(torch.as_tensor(X, dtype=DTYPE), self.theta_at(int(t)))[..., 0]

    def read_observables(self) -> Tensor:
        """One reading at ``t = n_reads`` (the unknowns set to :math:`\\theta(t)` first)."""
        self.theta = self.theta_at(self.n_reads)
        self.last_true_observables = self.true_observables(self._x)
        out = super().read_observables()
        self.n_reads += 1
        return out


def ring_drift_machine(
    seed: int, family: str, *, noise: float = 0.04, ring=None, draw_seed: int | None = None
) -> RingDriftMachine:
    """Machine ``seed`` of ``ring`` (default SPEAR3) with its own loss-rate map, drifting as
    ``family`` with draws of ``draw_seed`` (default ``seed``); noise seed ``seed``."""
    from pigp_torch.bench.machines import benchmark_ring
    from pigp_torch.machines.ring.spec import as_ring_spec

    sim = benchmark_ring(int(seed), as_ring_spec(ring), True)
    theta = draw_theta(sim, family, int(seed if draw_seed is None else draw_seed))
    return RingDriftMachine(ring_machine_model(sim), theta, noise=noise, seed=int(seed))


def gain_series(
    machine: RingDriftMachine, X, *, grid: int = 50, n_starts: int = 8
) -> tuple[np.ndarray, np.ndarray]:
    r"""Gain against the moving optimum of settings ``X`` (``T x K``, row ``t`` read at reading
    ``t``): :math:`(f_t(x_t) - f_t(0)) / (f^*_t - f_t(0))` and :math:`f^*_t` (mA/min), with
    :math:`f^*` searched every ``grid`` readings and on both sides of a step (warm-started,
    :func:`~pigp_torch.machines.drift.optimum_track`) and linearly interpolated between.

    Returns:
        ``(gain, f_star)``: two ``T`` arrays.
    """
    X = torch.as_tensor(X, dtype=DTYPE)
    T = X.shape[0]
    times = [*range(0, T, max(1, int(grid))), T - 1]
    if "step" in machine.theta_at.components and 0 < STEP_AT < T:  # both sides of the jump
        times += [STEP_AT - 1, STEP_AT]
    with torch.enable_grad():
        grid_t, _, F = optimum_track(
            lambda t: lambda Z: machine.loss_rate_at(Z, t),
            machine.bounds,
            sorted(set(times)),
            n_starts=n_starts,
            x_start=torch.zeros(X.shape[1], dtype=DTYPE),
        )
    f_star = interpolate_track(grid_t, F, np.arange(T))
    thetas = torch.stack([machine.theta_at(t) for t in range(T)])
    with torch.no_grad():
        f_x = machine.model.observe(X, thetas)[:, 0].numpy()
        f0 = machine.model.observe(torch.zeros_like(X), thetas)[:, 0].numpy()
    return (f_x - f0) / (f_star - f0), f_star
