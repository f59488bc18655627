"""RingCoupling: the same machinery for any ring and knobs (lattice files, element names)."""

import shutil

import at
import numpy as np
import pytest
import torch

from pigp_torch.simulation import LOSS_RATE_MAP, RingCoupling, Spear3Coupling
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
    """Without a loss-rate map, seed 1 of a user's ring reads 0.5 mA/min at zero knobs and
    1.7 at its optimum; other seeds share that map."""
    path = tmp_path / "design.json"
    shutil.copy(deck_path("design"), path)
    knobs = ["01G-QSS4", "02G-QSS3", "05G-QSS3"]
    ref = RingCoupling(path, knobs, 5.15e-4)
    assert float(ref.loss_rate(torch.zeros(3, dtype=D))) == pytest.approx(0.5, abs=1e-6)
    assert ref.optimum()[1] == pytest.approx(1.7, abs=1e-5)
    other = ref.with_seed(2)
    assert other.loss_rate_map == ref.loss_rate_map
    assert other.error_scale != ref.error_scale
    np.testing.assert_allclose(ref.bounds.numpy(), [[-30.0] * 3, [30.0] * 3])
