r"""Wrong-model cases of the ARES-EA task: the MACHINE departs from what the model assumes.

A method's model of the segment (e.g. ``ares-physics``) keeps the published prior ranges of
``lattice.json`` and the nominal magnet calibration; a case changes only the simulated machine a
trial runs on, deterministically per trial (the same trial gives the same machine every time).
The target, the start setting and the knob bounds are the trial's own.

* ``none``: the published trial, unchanged.
* ``beam-outside``: the incoming beam's eight transverse parameters lie outside their prior ranges.
  With :math:`u \sim U[1.25, 2]` drawn per parameter (generator seeded with
  :data:`CASE_SEED` + the trial's number): each centroid (:math:`\mu_x, \mu_y` in m,
  :math:`\mu_{x'}, \mu_{y'}` in rad; ranges :math:`\pm a` symmetric about 0) becomes
  :math:`\pm u\,a` with the sign of the trial's own value (+ for 0), i.e. 1.25–2× the range's
  limit; each rms size and divergence (:math:`\sigma_x, \sigma_y` in m, :math:`\sigma_{x'},
  \sigma_{y'}` in rad; ranges :math:`[l, h]`) becomes :math:`u\,h`, 1.25–2× the range's upper
  limit. Energy, bunch length and energy spread stay the trial's.
* ``misalign-3x``: every misalignment (three quadrupoles and the screen, x and y) is 3× the
  trial's, so the eight lie in ±1.5 mm, 3× the prior range ±0.5 mm; a trial's misalignment
  above 1/6 mm in magnitude lands outside the range.
* ``quad-cal-10``: the three quadrupoles act with :math:`1.10\,k_1` of their setting (a
  calibration 10 % off, e.g. a current-to-gradient factor); the correctors act as set.
  The knob readback and the logs keep the setting, as on a machine whose calibration is wrong.
"""

from __future__ import annotations

from dataclasses import replace

import torch

from pigp_torch._utils import DTYPE
from pigp_torch.machines.ares_ea.simulation import (
    INCOMING_NAMES,
    KNOB_NAMES,
    AresSegment,
    AresTrial,
    load_lattice,
)

#: The named cases, in the order tables list them (module docstring).
MODEL_ERROR_CASES: tuple[str, ...] = ("none", "beam-outside", "misalign-3x", "quad-cal-10")
#: One-line statements of the cases (for tables and ``--help``).
CASE_TEXT: dict[str, str] = {
    "none": "the published trial",
    "beam-outside": "incoming centroids, sizes and divergences 1.25-2x the prior range's limits",
    "misalign-3x": "misalignments 3x the trial's (+-1.5 mm, 3x the prior range)",
    "quad-cal-10": "quadrupoles act with 1.10 x the set k1",
}
#: Base seed of the ``beam-outside`` draws (the trial's number is added).
CASE_SEED: int = 37_000
#: Misalignment factor of ``misalign-3x``.
MISALIGN_FACTOR: float = 3.0
#: Quadrupole calibration factor of ``quad-cal-10``.
QUAD_CALIBRATION: float = 1.10
#: Range of the factor :math:`u` of ``beam-outside`` (multiples of a range limit).
OUTSIDE_FACTOR: tuple[float, float] = (1.25, 2.0)

_CENTROIDS = ("mu_x", "mu_xp", "mu_y", "mu_yp")
_SIZES = ("sigma_x", "sigma_xp", "sigma_y", "sigma_yp")
_QUADS = ("AREAMQZM1", "AREAMQZM2", "AREAMQZM3")


def check_case(case: str) -> str:
    """``case`` if it is one of :data:`MODEL_ERROR_CASES`.

    Raises:
        ValueError: an unknown case (one line, naming the known ones).
    """
    if case not in MODEL_ERROR_CASES:
        raise ValueError(f"unknown model-error case {case!r}; known: {list(MODEL_ERROR_CASES)}")
    return case


def beam_outside(trial: AresTrial, lattice: dict | None = None) -> torch.Tensor:
    """``11`` incoming beam of ``beam-outside`` for ``trial`` (module docstring; SI units)."""
    lattice = load_lattice() if lattice is None else lattice
    rng = lattice["incoming_beam_ranges"]
    if list(rng["order"]) != list(INCOMING_NAMES):
        raise ValueError(f"lattice incoming-beam order {rng['order']} is not {INCOMING_NAMES}")
    lo = torch.tensor(rng["low"], dtype=DTYPE)
    hi = torch.tensor(rng["high"], dtype=DTYPE)
    gen = torch.Generator().manual_seed(CASE_SEED + int(trial.index))
    a, b = OUTSIDE_FACTOR
    u = a + (b - a) * torch.rand(len(_CENTROIDS) + len(_SIZES), generator=gen, dtype=DTYPE)
    inc = trial.incoming.to(DTYPE).clone()
    for k, name in enumerate(_CENTROIDS):
        i = INCOMING_NAMES.index(name)
        sign = -1.0 if float(inc[i]) < 0 else 1.0
        inc[i] = sign * u[k] * torch.maximum(hi[i].abs(), lo[i].abs())
    for k, name in enumerate(_SIZES, start=len(_CENTROIDS)):
        i = INCOMING_NAMES.index(name)
        inc[i] = u[k] * hi[i]
    return inc


def case_trial(trial: AresTrial, case: str, lattice: dict | None = None) -> AresTrial:
    """The trial the machine of ``case`` runs (incoming beam and misalignments changed as
    stated; ``quad-cal-10`` and ``none``: the trial itself)."""
    check_case(case)
    if case == "beam-outside":
        return replace(trial, incoming=beam_outside(trial, lattice))
    if case == "misalign-3x":
        return replace(trial, misalignments=MISALIGN_FACTOR * trial.misalignments.to(DTYPE))
    return trial


def knob_gain(case: str) -> torch.Tensor:
    """``5`` factors from the knob settings to what the magnets do (1 but for ``quad-cal-10``,
    whose quadrupoles get :data:`QUAD_CALIBRATION`)."""
    check_case(case)
    gain = torch.ones(len(KNOB_NAMES), dtype=DTYPE)
    if case == "quad-cal-10":
        for name in _QUADS:
            gain[KNOB_NAMES.index(name)] = QUAD_CALIBRATION
    return gain


class CalibratedSegment(AresSegment):
    r"""An :class:`AresSegment` whose magnets act with ``gain`` × their setting:
    :meth:`observe` tracks ``knobs * gain`` (``5`` factors, broadcast over the batch).

    Args:
        gain: ``5`` factors (default :func:`knob_gain` of ``"quad-cal-10"``).
        lattice, dtype: as :class:`AresSegment`.
    """

    def __init__(self, gain=None, lattice: dict | None = None, dtype: torch.dtype = DTYPE):
        super().__init__(lattice, dtype)
        g = knob_gain("quad-cal-10") if gain is None else torch.as_tensor(gain, dtype=dtype)
        if g.shape != (len(KNOB_NAMES),):
            raise ValueError(f"knob gain needs {len(KNOB_NAMES)} factors, got {tuple(g.shape)}")
        self.gain = g.to(dtype)

    def observe(self, knobs, incoming, misalignments, energy=None) -> torch.Tensor:
        """:meth:`AresSegment.observe` at ``knobs * gain``."""
        x = torch.as_tensor(knobs, dtype=self.dtype) * self.gain
        return super().observe(x, incoming, misalignments, energy)


def case_machine_parts(
    trial: AresTrial, case: str, lattice: dict | None = None
) -> tuple[AresTrial, AresSegment]:
    """``(trial, segment)`` of the machine of ``case``: the trial it runs and the segment it is
    tracked through (a :class:`CalibratedSegment` for ``quad-cal-10``, else a plain one)."""
    check_case(case)
    lattice = load_lattice() if lattice is None else lattice
    segment = CalibratedSegment(knob_gain(case), lattice) if case == "quad-cal-10" else None
    return case_trial(trial, case, lattice), segment or AresSegment(lattice)
