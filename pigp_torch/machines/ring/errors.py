r"""Seeded coupling errors: quadrupole rolls and vertical sextupole offsets.

Both are the usual sources of betatron coupling in a storage ring: a quadrupole rolled by θ
adds a skew gradient ≈ 2θ·K1, and a sextupole displaced vertically by Δy adds a skew gradient
K2·Δy (feed-down). Errors are drawn from Gaussians cut at 2.5σ (resampled beyond the cut); the
nominal rms values are those of the SPEAR3 coupling studies (230 µrad, 76 µm). One global
``scale`` multiplies every error; :class:`~pigp_torch.machines.ring.ring.RingCoupling`
calibrates it per seed so that the skews-off emittance ratio hits its target.

A magnet that carries a thin skew winding is split in two halves around it; the two halves are one
magnet (one roll, one offset): :func:`magnets` groups them.
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
        quads = magnets(ring, at.Quadrupole)
        sexts = magnets(ring, at.Sextupole)
        if len(quads) != self.quad_rolls.size or len(sexts) != self.sext_offsets.size:
            raise ValueError("error pattern does not match the ring's magnets")
        for halves, r in zip(quads, self.quad_rolls, strict=True):
            for i in halves:
                at.tilt_elem(ring[i], float(scale * QUAD_ROLL_RMS * r))
        for halves, r in zip(sexts, self.sext_offsets, strict=True):
            for i in halves:
                at.shift_elem(ring[i], 0.0, float(scale * SEXT_OFFSET_RMS * r))


def magnets(ring: at.Lattice, kind=at.Sextupole) -> list[tuple[int, ...]]:
    """Element indices of each magnet of class ``kind`` (``at.Sextupole`` or ``at.Quadrupole``).

    Two elements of ``kind`` with the same family name and length on either side of one
    ``at.ThinMultipole`` (a winding between the halves of a split magnet) are one magnet; every
    other element of ``kind`` is a magnet of its own. Dipoles are never counted as quadrupoles.
    """
    out, i, n = [], 0, len(ring)
    while i < n:
        e = ring[i]
        if type(e) is kind:
            if (
                i + 2 < n
                and isinstance(ring[i + 1], at.ThinMultipole)
                and type(ring[i + 2]) is kind
                and ring[i + 2].FamName == e.FamName
                and abs(ring[i + 2].Length - e.Length) < 1e-12
            ):
                out.append((i, i + 2))
                i += 3
                continue
            out.append((i,))
        i += 1
    return out


def magnet_counts(ring: at.Lattice) -> tuple[int, int]:
    """``(quadrupoles, sextupoles)``: the magnet counts an error pattern of ``ring`` needs."""
    return len(magnets(ring, at.Quadrupole)), len(magnets(ring, at.Sextupole))
