r"""Lattice decks as element tables, and the pyAT rings built from them.

An element table is plain JSON data: a ``header`` (provenance, the numbers pyAT computes for the
deck, the skew-winding map and calibration) and ``elements`` in ring order, each a dict with
``type`` (``drift``, ``bend``, ``quadrupole``, ``sextupole``, ``corrector``, ``rfcavity``,
``marker``, ``aperture``), ``fam`` (family name), ``L`` (m) and the type's fields: ``K`` (K1 in
1/m², also the combined-function gradient of a bend), ``angle``, ``e1``, ``e2`` (rad), ``h``
(sextupole K2 = pyAT ``PolynomB[2]``, 1/m³), ``voltage`` (V), ``freq`` (Hz), ``harm``; a sextupole
may carry ``winding``, the control-system name of the skew-quadrupole winding on its coils.

:func:`ring_from_table` turns a table into a radiating (6-D) pyAT ring. Markers and apertures are
dropped (they do nothing to the linear optics), correctors become drifts of their length (their
kick is zero at the working point), and every sextupole with a winding is split in two halves with
a thin skew quadrupole (``at.ThinMultipole`` named after the winding, ``PolynomA[1]`` = K1s·L in
1/m, zero) between them.

Shipped decks (:data:`DECKS`, files in ``pigp_torch/machines/ring/data/`` with their provenance
headers):

=================  =======================  ===============  ===========
``optics``         deck                     tunes            εx (nm)
=================  =======================  ===============  ===========
``"user"``         SPEAR3 user mode sp3v82  14.13 / 6.22     17.9
``"design"``       SPEAR3 design sp3v81f    14.19 / 5.23     18.0
``"low_emittance"`` sp3v81f with dispersion  14.19 / 5.23     11.4
                   leaked into the straights
=================  =======================  ===============  ===========
"""

from __future__ import annotations

import copy
import functools
import json
from importlib import resources
from pathlib import Path

import at
import numpy as np

#: SPEAR3 beam energy (eV); the element tables carry no energy.
SPEAR3_ENERGY = 3.0e9

#: ``optics`` name -> shipped element-table file (in ``pigp_torch/machines/ring/data``).
DECKS = {
    "user": "spear3_sp3v82_elements.json",
    "design": "spear3_sp3v81f_elements.json",
    "low_emittance": "spear3_sp3v81f_etaleak_elements.json",
}


def deck_path(optics: str) -> Path:
    """Path of the shipped element table of ``optics`` (a key of :data:`DECKS`).

    Raises:
        ValueError: unknown ``optics``.
    """
    if optics not in DECKS:
        raise ValueError(f"unknown optics {optics!r}; choose one of {sorted(DECKS)}")
    return Path(str(resources.files("pigp_torch.machines.ring") / "data" / DECKS[optics]))


@functools.lru_cache(maxsize=8)
def _read_table(path: str) -> dict:
    with open(path, encoding="utf-8") as fh:
        table = json.load(fh)
    if not isinstance(table, dict) or not isinstance(table.get("elements"), list):
        raise ValueError(f"{path}: not an element table (needs a list under 'elements')")
    return table


def load_table(source) -> dict:
    """An element table: a key of :data:`DECKS`, or the path of a JSON table (a deep copy).

    Raises:
        ValueError: unknown deck name, or a file that is not an element table.
        FileNotFoundError: no such file.
    """
    path = deck_path(source) if str(source) in DECKS else Path(source)
    if not path.is_file():
        raise FileNotFoundError(f"no element table at {path}")
    return copy.deepcopy(_read_table(str(path.resolve())))


def _element(e: dict, energy: float) -> list:
    """The pyAT element(s) of one table row (an empty list for markers and apertures)."""
    kind, fam, length = e["type"], str(e["fam"]), float(e.get("L", 0.0))
    if kind in ("marker", "aperture"):
        return []
    if kind in ("drift", "corrector"):
        return [at.Drift(fam, length)] if length > 0 else []
    if kind == "quadrupole":
        return [at.Quadrupole(fam, length, float(e["K"]))]
    if kind == "bend":
        return [
            at.Dipole(
                fam,
                length,
                float(e["angle"]),
                float(e.get("K", 0.0)),
                EntranceAngle=float(e.get("e1", 0.0)),
                ExitAngle=float(e.get("e2", 0.0)),
            )
        ]
    if kind == "sextupole":
        h = float(e.get("h", 0.0))
        winding = e.get("winding")
        if not winding:
            return [at.Sextupole(fam, length, h)]
        return [
            at.Sextupole(fam, length / 2, h),
            at.ThinMultipole(str(winding), [0.0, 0.0], [0.0, 0.0]),
            at.Sextupole(fam, length / 2, h),
        ]
    if kind == "rfcavity":
        return [
            at.RFCavity(
                fam, length, float(e["voltage"]), float(e["freq"]), round(e["harm"]), energy
            )
        ]
    raise ValueError(f"element {fam!r}: unknown type {kind!r}")


def ring_from_table(table, *, energy: float = SPEAR3_ENERGY, radiation: bool = True) -> at.Lattice:
    """A pyAT ring from an element table (see the module docstring for the mapping).

    Args:
        table: an element table (dict), a key of :data:`DECKS` or a JSON path.
        energy: beam energy (eV), default 3 GeV.
        radiation: make it radiate (default; :func:`make_radiating`): a ring whose
            equilibrium emittances ``at.ohmi_envelope`` computes.

    Returns:
        A fresh ``at.Lattice`` (the caller may modify it).

    Raises:
        ValueError: an unknown element type, or no RF cavity in a radiating ring.
    """
    if not isinstance(table, dict):
        table = load_table(table)
    elems = [el for row in table["elements"] for el in _element(row, energy)]
    name = str(table.get("header", {}).get("deck", "ring")).split(":")[0]
    ring = at.Lattice(elems, name=name, energy=float(energy), periodicity=1)
    if radiation:
        if not any(isinstance(el, at.RFCavity) for el in ring):
            raise ValueError("a radiating ring needs an RF cavity (type 'rfcavity')")
        make_radiating(ring)
    return ring


def make_radiating(ring: at.Lattice) -> None:
    """Turn a 4-D ring into a radiating 6-D one in place, on the design orbit.

    ``enable_6d()``; the RF frequency set to the harmonic of the revolution frequency of the ring
    as built (``set_rf_frequency()``: a deck's own frequency, computed from a slightly different
    circumference, would shift the mean energy by ~1e-4 and the orbit in the arcs by tens of µm);
    ``tapering()`` (magnets scaled to the local energy of the radiation sawtooth).
    """
    ring.enable_6d()
    ring.set_rf_frequency()
    at.tapering(ring)


@functools.lru_cache(maxsize=4)
def _shipped_ring(optics: str) -> at.Lattice:
    return ring_from_table(load_table(optics))


def spear3_ring(optics: str = "user") -> at.Lattice:
    """The radiating SPEAR3 ring of a shipped deck, all 72 windings at zero (a fresh copy).

    Args:
        optics: ``"user"`` (default, the user-mode deck sp3v82), ``"design"`` (sp3v81f) or
            ``"low_emittance"`` (sp3v81f with dispersion in the straights).
    """
    deck_path(optics)  # validates the name
    return _shipped_ring(optics).deepcopy()


def spear3_header(optics: str = "user") -> dict:
    """The provenance header of a shipped SPEAR3 deck (windings, calibration, pyAT numbers)."""
    return load_table(optics)["header"]


def ring_parameters(ring: at.Lattice) -> dict:
    """Tunes and chromaticities (4-D, tunes with their integer part), εx (nm, ohmi_envelope),
    U0 (keV), σδ and damping times (ms) of a radiating (6-D) ring.
    """
    _, beam, _ = at.ohmi_envelope(ring)
    rp = ring.radiation_parameters()
    flat = ring.disable_6d(copy=True)
    _, optics4, _ = at.get_optics(flat, get_chrom=True)
    eps = np.sort(np.asarray(beam.mode_emittances, dtype=float))
    return {
        "tunes": [float(v) for v in flat.get_tune(get_integer=True)[:2]],
        "chromaticity": [float(v) for v in optics4.chromaticity[:2]],
        "eps_x_nm": float(eps[1] * 1e9),
        "U0_keV": float(rp.U0 / 1e3),
        "sigma_delta": float(rp.sigma_e),
        "damping_times_ms": [float(t * 1e3) for t in np.asarray(rp.Tau)],
    }
