"""The SPEAR3 lattice decks: rings built from the shipped element tables give pyAT's numbers."""

import pytest

from pigp_torch.simulation import deck


@pytest.fixture(scope="module", params=sorted(deck.DECKS))
def built(request):
    optics = request.param
    ring = deck.spear3_ring(optics)
    return optics, ring, deck.ring_parameters(ring), deck.spear3_header(optics)["pyat_facts"]


def test_ring_matches_the_headers_pyat_numbers(built):
    """Tunes, chromaticity, εx, U0, σδ and damping times agree with the deck header within 1 %."""
    _, ring, got, facts = built
    assert ring.circumference == pytest.approx(facts["circumference_m"], rel=1e-9)
    for mine, theirs in zip(got["tunes"], facts["tunes"], strict=True):
        assert mine == pytest.approx(theirs, abs=1e-3)  # 1e-4 of the tune, well inside 1 %
    for mine, theirs in zip(got["chromaticity"], facts["chromaticity"], strict=True):
        assert mine == pytest.approx(theirs, abs=0.01)
    assert got["eps_x_nm"] == pytest.approx(facts["eps_x_nm_ohmi"], rel=0.01)
    assert got["U0_keV"] == pytest.approx(facts["U0_keV"], rel=0.01)
    assert got["sigma_delta"] == pytest.approx(facts["sigma_delta"], rel=0.01)
    for mine, theirs in zip(got["damping_times_ms"], facts["damping_times_ms"], strict=True):
        assert mine == pytest.approx(theirs, rel=0.01)


def test_user_mode_deck_is_the_operating_optics(built):
    """The user-mode deck runs at 14.13 / 6.22; the design decks at 14.19 / 5.23."""
    optics, _, got, _ = built
    expected = (14.13, 6.22) if optics == "user" else (14.19, 5.23)
    assert got["tunes"] == pytest.approx(list(expected), abs=2e-3)


def test_windings_sit_on_the_sextupoles_of_the_map():
    """Winding NNG-QSSk is the thin element in the middle of the (4(NN-1)+k)-th sextupole."""
    import at

    ring = deck.spear3_ring("user")
    sexts = [i for i, e in enumerate(ring) if isinstance(e, at.Sextupole)]
    assert len(sexts) == 144  # 72 magnets in halves
    for n, name in enumerate(["01G-QSS1", "05G-QSS3", "10G-QSS4", "18G-QSS4"]):
        girder, k = int(name[:2]), int(name[-1])
        first_half = sexts[2 * (4 * (girder - 1) + k - 1)]
        thin = ring[first_half + 1]
        assert isinstance(thin, at.ThinMultipole) and thin.FamName == name, n
        assert ring[first_half + 2].FamName == ring[first_half].FamName


def test_bad_deck_names_and_tables():
    """An unknown optics name or a file that is no element table is refused clearly."""
    with pytest.raises(ValueError, match="unknown optics"):
        deck.spear3_ring("achromat")
    with pytest.raises(ValueError, match="unknown type"):
        deck.ring_from_table({"elements": [{"type": "wiggler", "fam": "W", "L": 1.0}]})
    with pytest.raises(ValueError, match="RF cavity"):
        deck.ring_from_table({"elements": [{"type": "drift", "fam": "D", "L": 1.0}]})
