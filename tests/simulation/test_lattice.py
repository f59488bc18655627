"""Lattices and knobs: knob names resolved to elements, thin knobs inserted into the ring."""

import pytest

from pigp_torch.simulation import RingCoupling
from pigp_torch.simulation.deck import load_table, ring_from_table
from pigp_torch.simulation.lattice import insert_knobs, resolve_knob


def test_knob_names_resolve_or_fail_clearly():
    """Knob names: a unique family, FAM[n] or #index; ambiguous or missing names are refused."""
    ring = ring_from_table(load_table("user"))
    assert ring[resolve_knob(ring, "01G-QSS4")].FamName == "01G-QSS4"
    assert resolve_knob(ring, "#5") == 5
    with pytest.raises(ValueError, match="name one as SF"):
        resolve_knob(ring, "SF")
    with pytest.raises(ValueError, match="no element of family"):
        resolve_knob(ring, "NOPE")
    with pytest.raises(ValueError, match="cannot carry a skew winding"):
        insert_knobs(ring, ["DA1A"])
    with pytest.raises(ValueError, match="one value or one per knob"):
        RingCoupling(ring, ["01G-QSS4", "02G-QSS3"], [1e-3, 1e-3, 1e-3])
