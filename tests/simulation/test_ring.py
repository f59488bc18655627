"""RingCoupling: the same machinery for any ring and knobs (lattice files, element names)."""

import shutil

import at
import numpy as np
import pytest
import torch

from pigp_torch.simulation import (
    LOSS_RATE_MAP,
    RingCoupling,
    Spear3Coupling,
    calibrate_loss_rate_map,
)
from pigp_torch.simulation.calibration import MIN_BACKGROUND_SHARE
from pigp_torch.simulation.deck import deck_path, load_table, ring_from_table
from pigp_torch.simulation.lattice import insert_knobs, resolve_knob
from pigp_torch.simulation.spear3 import knob_calibration_for

D = torch.float64


def log_excess_precision(sim, x):
    """Σ = −H/2 of log(f − f∞) at ``x`` (1/unit²)."""

    def g(z):
        return torch.log(sim.loss_rate(z) - sim.loss_background)

    return -torch.autograd.functional.hessian(g, x) / 2


def test_saved_spear3_ring_loaded_as_a_file_gives_the_same_precision(tmp_path):
    """The SPEAR3 ring written with at.save_mat and loaded through the generic path: same
    calibrated machine and the same Σ = −H/2 at the optimum (1e-8)."""
    spear = Spear3Coupling(1)
    path = tmp_path / "spear3.mat"
    at.save_mat(spear.ideal_lattice, str(path))
    generic = RingCoupling(
        path,
        spear.knob_names,
        knob_calibration_for(spear.knob_names),
        error_seed=1,
        loss_rate_map=LOSS_RATE_MAP,
    )
    assert generic.error_scale == pytest.approx(spear.error_scale, rel=1e-8)
    x, _ = spear.optimum()
    a, b = log_excess_precision(spear, x), log_excess_precision(generic, x)
    assert float((a - b).norm() / a.norm()) < 1e-8


def test_knob_on_a_thick_sextupole_is_split_around_a_thin_winding():
    """A knob named by a sextupole element (FAM[n]) splits it into two halves around a thin
    winding, and acts like the SPEAR3 winding on that magnet (same Σ to 1e-3)."""
    table = load_table("user")
    for row in table["elements"]:
        row.pop("winding", None)  # whole sextupoles, no windings
    ring = ring_from_table(table)
    n_sext = sum(isinstance(e, at.Sextupole) for e in ring)
    assert n_sext == 72
    # 01G-QSS3 is the 3rd sextupole of the ring, the 2nd of family SFM
    assert resolve_knob(ring, "SFM[1]") == [i for i, e in enumerate(ring)
                                            if isinstance(e, at.Sextupole)][2]  # fmt: skip
    split, index = insert_knobs(ring, ["SFM[1]", "SDM[1]"])
    assert len(split) == len(ring) + 4
    assert isinstance(split[index[0]], at.ThinMultipole)
    assert split[index[0] - 1].Length == pytest.approx(0.105)
    names = ["01G-QSS3", "01G-QSS4"]
    generic = RingCoupling(
        ring, ["SFM[1]", "SDM[1]"], knob_calibration_for(names), loss_rate_map=LOSS_RATE_MAP
    )
    spear = Spear3Coupling(1, knobs=names)
    x = torch.tensor([5.0, -7.0], dtype=D)
    a, b = log_excess_precision(spear, x), log_excess_precision(generic, x)
    assert float((a - b).norm() / a.norm()) < 1e-3


def test_default_loss_rate_map_is_calibrated_on_error_seed_1(tmp_path):
    """Without a loss-rate map, seed 1 of a user's ring reads 0.5 mA/min at zero knobs; with three
    knobs the density rises only ~2.3x, too little for 1.7 mA/min at the optimum with a
    non-negative background, so the map keeps SPEAR3's background share and the optimum is
    lower. Every loss rate in the box (and on another seed) is positive, above f∞."""
    path = tmp_path / "design.json"
    shutil.copy(deck_path("design"), path)
    knobs = ["01G-QSS4", "02G-QSS3", "05G-QSS3"]
    ref = RingCoupling(path, knobs, 5.15e-4)
    f_inf = ref.loss_rate_map[0]
    zero = torch.zeros(3, dtype=D)
    assert float(ref.loss_rate(zero)) == pytest.approx(0.5, abs=1e-6)
    assert f_inf == pytest.approx(MIN_BACKGROUND_SHARE * 0.5, rel=1e-12)
    x_star, f_star = ref.optimum()
    ratio = float(ref.inv_sigma_xy(x_star) / ref.inv_sigma_xy(zero))
    assert 1.5 < ratio < 3.0
    assert f_star == pytest.approx(f_inf + (0.5 - f_inf) * ratio, rel=1e-9)
    assert 0.5 < f_star < 1.7
    other = ref.with_seed(2)
    assert other.loss_rate_map == ref.loss_rate_map
    assert other.error_scale != ref.error_scale
    np.testing.assert_allclose(ref.bounds.numpy(), [[-30.0] * 3, [30.0] * 3])
    box = (torch.rand(500, 3, generator=torch.Generator().manual_seed(0), dtype=D) * 2 - 1) * 30
    for sim in (ref, other):
        assert float(sim.loss_rate(box).min()) > f_inf > 0


class _Density:
    """A stand-in ring on [−1, 1]²: ⟨1/(σxσy)⟩ = p0 (r − (r − 1)|x − 0.5|²/0.5), p0 at zero
    knobs and the maximum r·p0 at x = (0.5, 0.5)."""

    dim = 2
    bounds = torch.tensor([[-1.0, -1.0], [1.0, 1.0]], dtype=D)

    def __init__(self, p0, r):
        self.p0, self.r = p0, r

    def inv_sigma_xy(self, x):
        x = torch.as_tensor(x, dtype=D)
        z = x - 0.5  # knobs off (x = 0) reads p0; the maximum r·p0 is at x = (0.5, 0.5)
        return self.p0 * (self.r - (self.r - 1) * (z * z).sum(-1) / 0.5)


@pytest.mark.parametrize("r", [1.2, 2.0, 3.4, 3.6, 6.0])
def test_loss_rate_map_anchors_or_keeps_a_non_negative_background(r):
    """Closed forms of the two branches (p* = r p0): both anchors where they give
    f∞ ≥ 0.196·off (r ≥ (1.7 − 0.098)/0.402 ≈ 3.985), else f∞ = 0.098 and the optimum
    0.098 + 0.402 r; the map is continuous at the boundary and f∞ is never negative."""
    sim = _Density(1e8, r)
    f_inf, g = calibrate_loss_rate_map(sim)
    floor = MIN_BACKGROUND_SHARE * 0.5
    assert f_inf + g * 1e8 == pytest.approx(0.5, rel=1e-9)
    r_min = (1.7 - floor) / (0.5 - floor)
    if r >= r_min:
        assert f_inf + g * r * 1e8 == pytest.approx(1.7, rel=1e-6)
        assert f_inf >= floor
    else:
        assert f_inf == pytest.approx(floor, rel=1e-12)
        assert f_inf + g * r * 1e8 == pytest.approx(floor + (0.5 - floor) * r, rel=1e-6)
    at_edge = calibrate_loss_rate_map(_Density(1e8, r_min * (1 + 1e-9)))
    assert at_edge[0] == pytest.approx(floor, rel=1e-6)
    with pytest.raises(ValueError, match="0 < off < best"):
        calibrate_loss_rate_map(sim, off=0.5, best=0.4)
