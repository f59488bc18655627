r"""pyAT reference path: the same observables straight from ``at.ohmi_envelope`` (slow, exact).

Used to validate the fast model (:mod:`pigp_torch.machines.ring.linear_model`) and to precompute it.
"""

from __future__ import annotations

import warnings

import at
import numpy as np


def observation_points(ring: at.Lattice) -> tuple[np.ndarray, np.ndarray]:
    r"""Observation points of the ring average ⟨1/(σxσy)⟩ and their weights.

    Every element of non-zero length contributes its entrance value weighted by its length over the
    circumference (a left Riemann sum over elements; the same definition on both paths).
    """
    lengths = np.array([getattr(e, "Length", 0.0) for e in ring])
    idx = np.flatnonzero(lengths > 0)
    return idx, lengths[idx] / lengths.sum()


def set_knobs(ring: at.Lattice, knob_index, values) -> None:
    """Set the integrated skew strength K1sL (PolynomA[1]) of the thin windings in place."""
    for i, v in zip(knob_index, values, strict=True):
        ring[i].PolynomA[1] = float(v)


def mode_emittances(ring: at.Lattice) -> np.ndarray:
    """Sorted eigen-emittances (ascending: εy, εx, εz) at the current settings (ohmi_envelope)."""
    _, beam, _ = at.ohmi_envelope(ring)
    return np.sort(np.asarray(beam.mode_emittances, dtype=float))


def envelope_at(ring: at.Lattice, obs_index, obs_weight) -> tuple[np.ndarray, float]:
    """Sorted eigen-emittances and ⟨1/(σxσy)⟩ at the current settings (one ohmi_envelope pass)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        _, beam, data = at.ohmi_envelope(ring, refpts=obs_index)
    r66 = data.r66
    inv_sig = float(np.sum(obs_weight / np.sqrt(r66[:, 0, 0] * r66[:, 2, 2])))
    return np.sort(np.asarray(beam.mode_emittances, dtype=float)), inv_sig


def cumulative_matrices(ring: at.Lattice) -> dict:
    r"""Cumulative transfer and diffusion matrices at every element entrance and the ring end.

    From one ``ohmi_envelope`` pass with the knobs as set: :math:`R_j = m_j R_0 m_j^T + B_j`
    gives the cumulative diffusion :math:`B_j` from the returned beam matrices :math:`R_j` and
    transfer matrices :math:`m_j` (public API only).
    """
    emit0, _, data = at.ohmi_envelope(ring, refpts=at.All)
    m66 = np.asarray(data.m66)
    r0 = np.asarray(emit0.r66)
    bbcum = np.asarray(data.r66) - m66 @ r0 @ m66.transpose(0, 2, 1)
    return {"m66": m66, "bbcum": bbcum, "one_turn": np.asarray(emit0.m66)}


def thin_knob_generator() -> np.ndarray:
    """``E = dK/da`` of a thin skew quadrupole of integrated strength ``a``, from pyAT itself."""
    a = 1e-3
    elem = at.ThinMultipole("probe", [0.0, a], [0.0, 0.0])
    return (at.find_elem_m66(elem) - np.eye(6)) / a
