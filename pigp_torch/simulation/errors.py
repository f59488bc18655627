r"""Seeded coupling errors: quadrupole rolls and vertical sextupole offsets.

Both are the usual sources of betatron coupling in a storage ring: a quadrupole rolled by θ
adds a skew gradient ≈ 2θ·K1, and a sextupole displaced vertically by Δy adds a skew gradient
K2·Δy (feed-down). Errors are drawn from Gaussians cut at 2.5σ (resampled beyond the cut); the
nominal rms values come from the SPEAR3 feasibility study (DESIGN.md §2). One global ``scale``
multiplies every error; :class:`~pigp_torch.simulation.Spear3Coupling` calibrates it per seed so
that the skews-off emittance ratio hits its target.
"""

from __future__ import annotations

from dataclasses import dataclass

import at
import numpy as np

QUAD_ROLL_RMS = 230e-6  # rad
SEXT_OFFSET_RMS = 76e-6  # m
CUT = 2.5  # Gaussians cut at 2.5 sigma


def truncated_normal(rng: np.random.Generator, n: int, cut: float = CUT) -> np.ndarray:
    """``n`` standard-normal draws, each redrawn until it lies within ``±cut``."""
    out = rng.standard_normal(n)
    bad = np.abs(out) > cut
    while bad.any():  # expected ~1.2 % redraws per pass: terminates after a few passes
        out[bad] = rng.standard_normal(int(bad.sum()))
        bad = np.abs(out) > cut
    return out


@dataclass(frozen=True)
class CouplingErrors:
    """Unit-rms error pattern of one seed; physical errors are ``scale * rms * pattern``.

    Attributes:
        seed: the error seed.
        quad_rolls: one standard-normal draw per quadrupole (in lattice order).
        sext_offsets: one standard-normal draw per sextupole magnet (both halves move together).
    """

    seed: int
    quad_rolls: np.ndarray
    sext_offsets: np.ndarray

    @classmethod
    def draw(cls, seed: int, n_quads: int, n_sexts: int) -> CouplingErrors:
        rng = np.random.default_rng(seed)
        return cls(seed, truncated_normal(rng, n_quads), truncated_normal(rng, n_sexts))

    def apply(self, ring: at.Lattice, scale: float) -> None:
        """Roll the quadrupoles and displace the sextupoles of ``ring`` in place."""
        quads = [i for i, e in enumerate(ring) if isinstance(e, at.Quadrupole)]
        sexts = sextupole_magnets(ring)
        if len(quads) != self.quad_rolls.size or len(sexts) != self.sext_offsets.size:
            raise ValueError("error pattern does not match the ring's magnets")
        for i, r in zip(quads, self.quad_rolls, strict=True):
            at.tilt_elem(ring[i], float(scale * QUAD_ROLL_RMS * r))
        for halves, r in zip(sexts, self.sext_offsets, strict=True):
            for i in halves:
                at.shift_elem(ring[i], 0.0, float(scale * SEXT_OFFSET_RMS * r))


def sextupole_magnets(ring: at.Lattice) -> list[tuple[int, ...]]:
    """Indices of each sextupole magnet: consecutive halves (around a thin winding) form one."""
    magnets, current = [], []
    for i, e in enumerate(ring):
        if isinstance(e, at.Sextupole):
            current.append(i)
            if len(current) == 2:
                magnets.append(tuple(current))
                current = []
        elif current and not isinstance(e, at.ThinMultipole):
            raise ValueError(f"sextupole half at {current[0]} is not followed by its twin")
    return magnets
