r"""Drift and reality-gap families of simulated ARES-EA machines (docs/drift_families.md).

A family is a set of *components*; a machine of a family is one published trial (its target, its
incoming beam and misalignments) changed by those components, drawn deterministically from
``(trial, seed)`` (:func:`draw_gaps`; every component is drawn for every family, in one order, so
the ``beam-linear`` drift of trial 3, seed 101 is the linear part of its ``drift`` machine).
The reading count :math:`t` is the clock (readings at a steady rate); :data:`DURATION` = 300
readings is "a run".

Components (magnitudes: the module's constants):

* ``linear``: the incoming centroid moves linearly: :math:`\mu_x, \mu_y` each by
  :data:`LINEAR_POSITION_M` (drawn, random sign) and :math:`\mu_{x'}, \mu_{y'}` by
  :data:`LINEAR_ANGLE_RAD` over a run; the rms sizes :math:`\sigma_x, \sigma_y` by a relative
  :data:`LINEAR_SIZE_REL` of the trial's over a run.
* ``walk``: a random walk of the incoming centroid, :data:`WALK_POSITION_M` and
  :data:`WALK_ANGLE_RAD` standard deviation per reading.
* ``step``: at reading :data:`STEP_AT` the incoming centroid jumps (a re-pointed gun laser): by
  :data:`STEP_POSITION_M` in a random direction of :math:`(\mu_x, \mu_y)` and
  :data:`STEP_ANGLE_RAD` in a random direction of :math:`(\mu_{x'}, \mu_{y'})`.
* ``hysteresis``: every magnet acts with the play operator of its setpoint history
  (:class:`~pigp_torch.machines.drift.PlayHysteresis`), half width :data:`PLAY_WIDTH` (quads
  0.2 1/m², correctors 10 µrad); the state before the first setting is the start setting
  :math:`\pm w` (sign drawn per magnet: the magnet last came from below or from above).
* ``roll``: each quadrupole is rolled about the beam axis by :data:`ROLL_RAD` (random sign).
* ``corrector``: the acting corrector angles are a non-diagonal linear map of the set ones:
  :math:`\theta_{CV} = (1 + g_V)\theta^{set}_{CV} + c_{HV}\theta^{set}_{CH} + q_V k_{1,Q2}`,
  :math:`\theta_{CH} = (1 + g_H)\theta^{set}_{CH} + c_{VH}\theta^{set}_{CV} + q_H k_{1,Q3}`
  with calibration errors :math:`g` in :data:`CORRECTOR_GAIN`, cross-plane coefficients
  :math:`c` in :data:`CROSS_PLANE` (the other plane's kick is applied at the other corrector,
  0.40 m away) and quadrupole–steerer cross-talk :math:`q` in :data:`QUAD_STEERER` rad per 1/m².
* ``screen``: the screen blurs the beam with resolution :data:`SCREEN_RESOLUTION_M`
  (:math:`\sigma_{read} = \sqrt{\sigma^2 + r^2}`), the incoming centroid jitters shot to shot by
  :data:`JITTER_POSITION_M` and :data:`JITTER_ANGLE_RAD`, and every supply by a relative
  :data:`SUPPLY_JITTER_REL` of its setting.

Scoring: the *true* beam at reading :math:`t` (``last_true_observables``) is the beam of the
hidden state at :math:`t` (drift, acting fields, static gaps) without jitter, blur or screen
noise; the true MAE is its mean absolute error to the target.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from pigp_torch._utils import DTYPE
from pigp_torch.machines.ares_ea.machine import AresMachine
from pigp_torch.machines.ares_ea.simulation import INCOMING_NAMES, AresSegment, AresTrial
from pigp_torch.machines.drift import DriftPath, PlayHysteresis, family_components

#: A run (readings): the linear drifts' magnitudes are stated per run.
DURATION: int = 300
LINEAR_POSITION_M: tuple[float, float] = (20e-6, 60e-6)
LINEAR_ANGLE_RAD: tuple[float, float] = (2e-6, 6e-6)
LINEAR_SIZE_REL: tuple[float, float] = (-0.10, 0.10)
WALK_POSITION_M: float = 2e-6
WALK_ANGLE_RAD: float = 0.2e-6
STEP_AT: int = 150
STEP_POSITION_M: tuple[float, float] = (50e-6, 150e-6)
STEP_ANGLE_RAD: tuple[float, float] = (5e-6, 15e-6)
#: Play half widths of Q1, Q2, CV, Q3, CH (1/m², 1/m², rad, 1/m², rad).
PLAY_WIDTH: tuple[float, ...] = (0.2, 0.2, 10e-6, 0.2, 10e-6)
ROLL_RAD: tuple[float, float] = (1e-3, 4e-3)
CORRECTOR_GAIN: tuple[float, float] = (-0.05, 0.05)
CROSS_PLANE: tuple[float, float] = (-0.03, 0.03)
QUAD_STEERER: tuple[float, float] = (-2.8e-7, 2.8e-7)
SCREEN_RESOLUTION_M: float = 15e-6
JITTER_POSITION_M: float = 5e-6
JITTER_ANGLE_RAD: float = 0.5e-6
SUPPLY_JITTER_REL: float = 1e-4
#: Base of the draws' seeds: seed ``DRIFT_SEED + 1000 * seed + trial``.
DRIFT_SEED: int = 48_000

#: The families and their components (module docstring).
ARES_FAMILIES: dict[str, frozenset[str]] = {
    "none": frozenset(),
    "beam-linear": frozenset({"linear"}),
    "beam-walk": frozenset({"walk"}),
    "laser-step": frozenset({"step"}),
    "hysteresis": frozenset({"hysteresis"}),
    "drift": frozenset({"linear", "walk", "hysteresis"}),
    "drift-step": frozenset({"linear", "walk", "hysteresis", "step"}),
    "quad-roll": frozenset({"roll"}),
    "corrector-cal": frozenset({"corrector"}),
    "screen-jitter": frozenset({"screen"}),
    "static": frozenset({"roll", "corrector", "screen"}),
}
_I = {n: i for i, n in enumerate(INCOMING_NAMES)}


def check_family(family: str) -> frozenset[str]:
    """The components of ``family`` (ValueError: an unknown one)."""
    return family_components(ARES_FAMILIES, family, "ARES")


@dataclass(frozen=True)
class AresGaps:
    r"""What a machine of a family has that the trial lacks (module docstring).

    Attributes:
        family: the family's name; components: its components.
        drift: the incoming beam's offset :math:`\Delta(t)` (``11``, SI units), or ``None``.
        play: ``5`` play half widths (zeros: no hysteresis); play_sign: ``5`` signs of the
            initial state.
        tilt: ``3`` quadrupole rolls (rad).
        corrector: ``2 x 2`` map :math:`[[1+g_V, c_{HV}], [c_{VH}, 1+g_H]]` of the set angles
            (CV, CH) to the acting ones; quad_steerer: ``2`` :math:`(q_V, q_H)` (rad per 1/m²).
        resolution: screen resolution (m); jitter: ``11`` shot-to-shot sd of the incoming beam;
        supply_jitter: relative sd of every supply.
    """

    family: str
    components: frozenset[str]
    drift: DriftPath | None
    play: torch.Tensor
    play_sign: torch.Tensor
    tilt: torch.Tensor
    corrector: torch.Tensor
    quad_steerer: torch.Tensor
    resolution: float
    jitter: torch.Tensor
    supply_jitter: float


def _uniform(gen, lo_hi, n: int = 1) -> torch.Tensor:
    lo, hi = lo_hi
    return lo + (hi - lo) * torch.rand(n, generator=gen, dtype=DTYPE)


def _signs(gen, n: int) -> torch.Tensor:
    return torch.where(torch.rand(n, generator=gen, dtype=DTYPE) < 0.5, -1.0, 1.0).to(DTYPE)


def _direction(gen) -> torch.Tensor:
    phi = 2 * math.pi * float(torch.rand(1, generator=gen, dtype=DTYPE))
    return torch.tensor([math.cos(phi), math.sin(phi)], dtype=DTYPE)


def _drift_path(trial: AresTrial, c: frozenset[str], gen, seed: int) -> DriftPath | None:
    """The incoming beam's :class:`DriftPath` of components ``c`` (all draws made always)."""
    pos = _uniform(gen, LINEAR_POSITION_M, 2) * _signs(gen, 2)
    ang = _uniform(gen, LINEAR_ANGLE_RAD, 2) * _signs(gen, 2)
    size = _uniform(gen, LINEAR_SIZE_REL, 2)
    step_pos = _uniform(gen, STEP_POSITION_M)[0] * _direction(gen)
    step_ang = _uniform(gen, STEP_ANGLE_RAD)[0] * _direction(gen)
    if not c & {"linear", "walk", "step"}:
        return None
    n = len(INCOMING_NAMES)
    rate, walk, step = (torch.zeros(n, dtype=DTYPE) for _ in range(3))
    xs, ys = ("mu_x", "mu_y"), ("mu_xp", "mu_yp")
    for k, (p, a) in enumerate(zip(xs, ys, strict=True)):
        if "linear" in c:
            rate[_I[p]], rate[_I[a]] = pos[k] / DURATION, ang[k] / DURATION
        if "walk" in c:
            walk[_I[p]], walk[_I[a]] = WALK_POSITION_M, WALK_ANGLE_RAD
        if "step" in c:
            step[_I[p]], step[_I[a]] = step_pos[k], step_ang[k]
    if "linear" in c:
        for k, s in enumerate(("sigma_x", "sigma_y")):
            rate[_I[s]] = size[k] * trial.incoming[_I[s]] / DURATION
    return DriftPath(
        rate, walk, step, step_at=STEP_AT if "step" in c else None, seed=seed, horizon=DURATION
    )


def draw_gaps(trial: AresTrial, family: str, seed: int = 101) -> AresGaps:
    r"""The gaps of ``family``'s machine of ``trial`` with draw seed ``seed`` (module docstring;
    generator seeded with :data:`DRIFT_SEED` + 1000 ``seed`` + the trial's number)."""
    c = check_family(family)
    s = DRIFT_SEED + 1000 * int(seed) + int(trial.index)
    gen = torch.Generator().manual_seed(s)
    drift = _drift_path(trial, c, gen, s)
    play_sign = _signs(gen, 5)
    tilt = _uniform(gen, ROLL_RAD, 3) * _signs(gen, 3)
    gain = _uniform(gen, CORRECTOR_GAIN, 2)
    cross = _uniform(gen, CROSS_PLANE, 2)
    qs = _uniform(gen, QUAD_STEERER, 2)
    jitter = torch.zeros(len(INCOMING_NAMES), dtype=DTYPE)
    if "screen" in c:
        jitter[[_I["mu_x"], _I["mu_y"]]] = JITTER_POSITION_M
        jitter[[_I["mu_xp"], _I["mu_yp"]]] = JITTER_ANGLE_RAD
    corrector = torch.eye(2, dtype=DTYPE)
    if "corrector" in c:
        corrector = torch.tensor([[1 + gain[0], cross[0]], [cross[1], 1 + gain[1]]], dtype=DTYPE)
    return AresGaps(
        family=family,
        components=c,
        drift=drift,
        play=torch.tensor(PLAY_WIDTH, dtype=DTYPE) * (1.0 if "hysteresis" in c else 0.0),
        play_sign=play_sign,
        tilt=tilt if "roll" in c else torch.zeros(3, dtype=DTYPE),
        corrector=corrector,
        quad_steerer=qs if "corrector" in c else torch.zeros(2, dtype=DTYPE),
        resolution=SCREEN_RESOLUTION_M if "screen" in c else 0.0,
        jitter=jitter,
        supply_jitter=SUPPLY_JITTER_REL if "screen" in c else 0.0,
    )


class GapSegment(AresSegment):
    r"""An :class:`AresSegment` with rolled quadrupoles and the corrector map of ``gaps``
    (module docstring): :meth:`observe` tracks the acting knobs :meth:`acting_knobs` of the given
    ones (batched, differentiable).

    Args:
        gaps: the machine's :class:`AresGaps`.
        lattice, dtype: as :class:`AresSegment`.
    """

    def __init__(self, gaps: AresGaps, lattice: dict | None = None, dtype=DTYPE) -> None:
        super().__init__(lattice, dtype)
        self.gaps = gaps
        for q, tilt in zip(("AREAMQZM1", "AREAMQZM2", "AREAMQZM3"), gaps.tilt, strict=True):
            self._el[q].tilt = tilt.to(dtype)

    def acting_knobs(self, knobs) -> torch.Tensor:
        r"""``... x 5`` knobs the magnets act with: correctors through the map and cross-talk."""
        x = torch.as_tensor(knobs, dtype=self.dtype)
        M, q = self.gaps.corrector, self.gaps.quad_steerer
        cv = M[0, 0] * x[..., 2] + M[0, 1] * x[..., 4] + q[0] * x[..., 1]
        ch = M[1, 1] * x[..., 4] + M[1, 0] * x[..., 2] + q[1] * x[..., 3]
        return torch.stack([x[..., 0], x[..., 1], cv, x[..., 3], ch], -1)

    def observe(self, knobs, incoming, misalignments, energy=None) -> torch.Tensor:
        """:meth:`AresSegment.observe` at :meth:`acting_knobs` of ``knobs``."""
        return super().observe(self.acting_knobs(knobs), incoming, misalignments, energy)


class AresDriftMachine(AresMachine):
    r"""An :class:`~.machine.AresMachine` of a drift or reality-gap family (module docstring).

    Args:
        trial: the published trial; gaps: its :class:`AresGaps` (:func:`draw_gaps`).
        options: as :class:`~.machine.AresMachine` (``objective``, ``noise``, ``seed``, ...;
            ``seed`` also seeds the shot-to-shot jitter).

    Attributes:
        hysteresis: the magnets' :class:`~pigp_torch.machines.drift.PlayHysteresis`.
        last_true_observables: ``4`` true beam (m) of the last reading, ``None`` before it.
    """

    def __init__(self, trial: AresTrial, gaps: AresGaps, **options) -> None:
        options.setdefault("segment", GapSegment(gaps))
        super().__init__(trial, **options)
        self.gaps = gaps
        self.hysteresis = PlayHysteresis(gaps.play, self.get() + gaps.play * gaps.play_sign)
        self.last_true_observables: torch.Tensor | None = None

    def _apply(self, x: torch.Tensor) -> None:
        """The magnets follow the setpoint ``x`` through their hysteresis."""
        self.hysteresis.apply(x)

    def incoming_at(self, t: int) -> torch.Tensor:
        """``11`` incoming beam at reading ``t`` (SI units)."""
        inc = self.trial.incoming.to(DTYPE)
        return inc if self.gaps.drift is None else inc + self.gaps.drift(t)

    def true_observables_at(self, x, t: int) -> torch.Tensor:
        r"""Noise-free ``4`` (or ``N x 4``) beam (m) at settings ``x`` (``5`` or ``N x 5``)
        reached now from the present magnet state, with the drift of reading ``t``."""
        x = torch.as_tensor(x, dtype=DTYPE)
        with torch.no_grad():
            return self.segment.observe(
                self.hysteresis.acting(x), self.incoming_at(t), self.trial.misalignments
            )

    def true_observables(self, x) -> torch.Tensor:
        """:meth:`true_observables_at` the next reading (``t = n_reads``)."""
        return self.true_observables_at(x, self.n_reads)

    def read_observables(self) -> torch.Tensor:
        """One screen measurement (reading ``t = n_reads``): the true beam (kept in
        :attr:`last_true_observables`) with shot-to-shot jitter, the screen's blur and noise."""
        t, g, gen = self.n_reads, self.gaps, self._generator
        self.last_true_observables = self.true_observables_at(self._x, t)
        y = self.hysteresis.y
        if g.supply_jitter > 0 or bool((g.jitter > 0).any()):
            y = y * (1 + g.supply_jitter * torch.randn(5, generator=gen, dtype=DTYPE))
            inc = self.incoming_at(t) + g.jitter * torch.randn(11, generator=gen, dtype=DTYPE)
            with torch.no_grad():
                obs = self.segment.observe(y, inc, self.trial.misalignments)
        else:
            obs = self.last_true_observables.clone()
        if g.resolution > 0:
            obs[[1, 3]] = torch.sqrt(obs[[1, 3]] ** 2 + g.resolution**2)
        if self.noise > 0:
            obs = obs + self.noise * torch.randn(4, generator=gen, dtype=DTYPE)
            obs[[1, 3]] = obs[[1, 3]].abs()
        self.n_reads += 1
        self.last_observables = obs
        return obs.clone()


def ares_drift_machine(trial: AresTrial, family: str, seed: int = 101, **options):
    """The :class:`AresDriftMachine` of ``family`` for ``trial`` with draw seed ``seed`` (also
    the jitter's and screen noise's seed unless ``options`` give one)."""
    options.setdefault("seed", int(seed))
    return AresDriftMachine(trial, draw_gaps(trial, family, seed), **options)


def true_mae(machine: AresDriftMachine) -> float:
    """True MAE (m) of the machine's last reading: the mean absolute error of its true beam
    (:attr:`AresDriftMachine.last_true_observables`) to the target."""
    if machine.last_true_observables is None:
        raise ValueError("the machine has not been read yet")
    return float(machine.mae(machine.last_true_observables))
