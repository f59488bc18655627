"""The SPEAR3-like ring reproduces the public SPEAR3 facts it was built from."""

import at
import numpy as np
import pytest

from pigp_torch.simulation import lattice


@pytest.fixture(scope="module")
def ring():
    return lattice.build_ring("achromat")


def test_circumference_and_rf(ring):
    """Circumference 234.144 m; RF at harmonic 372 (476.3 MHz) with 3.2 MV."""
    assert ring.circumference == pytest.approx(234.144, abs=1e-9)
    cav = ring[at.RFCavity][0]
    assert cav.HarmNumber == 372
    assert cav.Voltage == pytest.approx(3.2e6)
    assert cav.Frequency == pytest.approx(476.3e6, rel=2e-4)


def test_tunes_include_integer_part(ring):
    """Betatron tunes are matched to 14.19 / 5.23 (integer parts from the phase advance)."""
    lin = ring.disable_6d(copy=True)
    _, _, el = at.get_optics(lin, refpts=at.All)  # all points: the phase is unwrapped
    tunes = el.mu[-1] / (2 * np.pi)
    assert tunes[0] == pytest.approx(14.19, abs=2e-3)
    assert tunes[1] == pytest.approx(5.23, abs=2e-3)


def test_chromaticity_matched(ring):
    """Linear chromaticity is matched to about +1 / +1.5."""
    chrom = ring.disable_6d(copy=True).get_chrom()[:2]
    np.testing.assert_allclose(chrom, [1.0, 1.5], atol=0.02)


def test_equilibrium_matches_spear3(ring):
    """Natural εx 10-20 nm (achromat), σδ ~9.5e-4, σz ~5 mm, damping times ~4.3/5.3/3.0 ms."""
    p = ring.envelope_parameters()
    assert 10e-9 < p.emittances[0] < 20e-9
    assert p.sigma_e == pytest.approx(9.5e-4, rel=0.05)
    assert p.sigma_l == pytest.approx(5e-3, rel=0.1)
    np.testing.assert_allclose(p.Tau * 1e3, [4.3, 5.3, 3.0], rtol=0.1)


def test_low_emittance_variant():
    """The low-emittance optics has dispersion in the straights and εx of about 10 nm."""
    p = lattice.build_ring("low_emittance").envelope_parameters()
    assert 8e-9 < p.emittances[0] < 12e-9


def test_72_windings_named_by_girder_and_position(ring):
    """Every sextupole carries a thin skew winding named NNG-QSSk (18 girders x 4 positions)."""
    names = lattice.knob_names_for("all72")
    assert len(names) == 72 and names[0] == "01G-QSS1" and names[-1] == "18G-QSS4"
    for name in names:
        (i,) = ring.get_uint32_index(name)
        assert isinstance(ring[i], at.ThinMultipole)
        assert isinstance(ring[i - 1], at.Sextupole) and isinstance(ring[i + 1], at.Sextupole)
    kinds = [ring[ring.get_uint32_index(n)[0] - 1].FamName for n in names[:4]]
    assert kinds == ["SD", "SF", "SF", "SD"]


def test_knob_selection():
    """Knob sets resolve to the SPEAR3 powered windings; bad names are refused."""
    assert len(lattice.knob_names_for("paper13")) == 13
    assert lattice.knob_names_for("powered14")[0] == "01G-QSS4"
    assert set(lattice.knob_names_for("paper13")) < set(lattice.knob_names_for("powered14"))
    with pytest.raises(ValueError, match="unknown winding"):
        lattice.knob_names_for(["01G-QSS9"])
    with pytest.raises(ValueError, match="unique"):
        lattice.knob_names_for(["01G-QSS4", "01G-QSS4"])
    with pytest.raises(ValueError, match="unknown optics"):
        lattice.build_ring("fodo")
