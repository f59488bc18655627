r"""``Spear3Coupling``: the real SPEAR3 ring and its skew windings, in amps.

SPEAR3 (3 GeV, 234.144 m, 18 girders: 14 standard double-bend cells and 4 matching cells in
girders 1, 9, 10 and 18) is built from its lattice deck (:mod:`~pigp_torch.machines.ring.deck`; the
user-mode deck sp3v82 by default, tunes 14.13 / 6.22). Each of its 72 sextupoles carries a
skew-quadrupole winding; winding ``NNG-QSSk`` sits on the (4(NN−1)+k)-th sextupole in ring order.
Knobs are set in **amps**; a winding's integrated skew strength is

.. math:: K_{1s}L = \kappa\, L_\text{sext}\, I,\qquad \kappa = 0.00245246\ \text{m}^{-2}/\text{A}

(the LOCO calibration of the windings), i.e. 5.15e-4 1/m per A on the 0.21 m magnets of the 13
default knobs; the windings' range is ±30 A.

Knob sets: ``"paper13"`` (default; the 13 windings of the physics-informed GP study: the 14
powered windings without 03G-QSS3), ``"powered14"``, ``"all72"``, or a list of winding names.

Loss-rate map: :data:`LOSS_RATE_MAP` (f∞, g) is one pair of constants for the ring, chosen so that
error seed 1 of the user-mode ring with the 13 default knobs has 0.5 mA/min with the skews off and
1.7 mA/min at its optimum (:func:`~pigp_torch.machines.ring.calibration.calibrate_loss_rate_map`
recomputes it; a test checks it still holds).
"""

from __future__ import annotations

from pigp_torch.machines.ring import deck as _deck
from pigp_torch.machines.ring.ring import TARGET_RATIO, RingCoupling

#: K1s per amp of a SPEAR3 skew winding, 1/(m² A) (multiply by the sextupole length for K1s·L)
SKEW_K_PER_A_M2 = 0.00245246
#: the windings' power-supply range, ±A
KNOB_LIMIT_A = 30.0
#: (f_inf [mA/min], g [mA/min m²]) of loss_rate = f_inf + g <1/(sigma_x sigma_y)>
LOSS_RATE_MAP = (0.098065, 4.778383e-09)

KNOB_SETS = ("paper13", "powered14", "all72")


def knob_names_for(knobs, optics: str = "user") -> list[str]:
    """Resolve a SPEAR3 knob selection to winding names (``NNG-QSSk``).

    Args:
        knobs: ``"paper13"``, ``"powered14"``, ``"all72"``, or a sequence of winding names.
        optics: the deck whose winding map is used.

    Raises:
        ValueError: an unknown set or winding name, repeated names, or an empty list.
    """
    header = _deck.spear3_header(optics)
    windings = header["windings"]
    if isinstance(knobs, str):
        if knobs == "paper13":
            return list(header["paper13_windings"])
        if knobs == "powered14":
            return list(header["powered_windings_mml_spear3init"])
        if knobs == "all72":
            return sorted(windings, key=lambda n: windings[n]["element_index"])
        raise ValueError(f"unknown knob set {knobs!r}: use one of {KNOB_SETS} or a list of names")
    names = [str(n) for n in knobs]
    bad = [n for n in names if n not in windings]
    if bad:
        raise ValueError(f"unknown winding names {bad}; names look like '01G-QSS4'")
    if len(set(names)) != len(names):
        raise ValueError("knob names must be unique")
    if not names:
        raise ValueError("at least one knob is needed")
    return names


def knob_calibration_for(names, optics: str = "user") -> list[float]:
    """K1s·L per amp (1/m/A) of each winding: :data:`SKEW_K_PER_A_M2` × its sextupole's length."""
    windings = _deck.spear3_header(optics)["windings"]
    return [SKEW_K_PER_A_M2 * float(windings[n]["length_m"]) for n in names]


class Spear3Coupling(RingCoupling):
    r"""The simulated SPEAR3 ring: εy and Touschek loss rate vs its skew windings (amps).

    Args:
        error_seed: seed of the coupling-error pattern (one "machine" per seed).
        knobs: ``"paper13"`` (default), ``"powered14"``, ``"all72"`` or a list of winding names
            like ``"01G-QSS4"``.
        optics: ``"user"`` (default, deck sp3v82, 14.13 / 6.22), ``"design"`` (sp3v81f,
            14.19 / 5.23) or ``"low_emittance"`` (sp3v81f with dispersion in the straights).
        target_ratio: skews-off εy/εx that the error scale is calibrated to (default 0.71 %).
        error_scale: use this global error scale instead of calibrating (1 = nominal rms).
        knob_limit: symmetric bound of each winding current (A), default 30.
        loss_rate_map: ``(f_inf, g)``; default :data:`LOSS_RATE_MAP`.

    Knob values are currents in amps, float64, ``(N, K)`` or ``(K,)``; ``bounds`` is ±30 A.
    Everything else is :class:`~pigp_torch.machines.ring.ring.RingCoupling`.
    """

    def __init__(
        self,
        error_seed: int = 1,
        *,
        knobs="paper13",
        optics: str = "user",
        target_ratio: float = TARGET_RATIO,
        error_scale: float | None = None,
        knob_limit: float = KNOB_LIMIT_A,
        loss_rate_map: tuple[float, float] | None = None,
    ) -> None:
        names = knob_names_for(knobs, optics)
        self.optics = optics
        super().__init__(
            _deck.spear3_ring(optics),
            names,
            knob_calibration_for(names, optics),
            knob_limit=knob_limit,
            knob_units="A",
            error_seed=error_seed,
            target_ratio=target_ratio,
            error_scale=error_scale,
            loss_rate_map=LOSS_RATE_MAP if loss_rate_map is None else loss_rate_map,
            name=f"SPEAR3 {optics}",
        )

    def __repr__(self) -> str:
        return (
            f"Spear3Coupling(error_seed={self.error_seed}, knobs={self.dim}, optics="
            f"{self.optics!r}, error_scale={self.error_scale:.4f})"
        )
