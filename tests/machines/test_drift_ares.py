"""ARES-EA drift and reality-gap families (pigp_torch.machines.ares_ea.drift): deterministic
per seed, magnitudes as documented, path-dependent hysteresis, the step at its reading, the
true-MAE score, and the static-gap model passing the machine-kind contract."""

from __future__ import annotations

from typing import ClassVar

import pytest
import torch

from pigp_torch.machines import KINDS
from pigp_torch.machines.ares_ea import drift as D
from pigp_torch.machines.ares_ea.simulation import INCOMING_NAMES, load_trials
from pigp_torch.machines.contract import MachineKindContract

I = {n: i for i, n in enumerate(INCOMING_NAMES)}


@pytest.fixture(scope="module")
def trials():
    return load_trials()


def test_every_family_is_listed_by_the_kind_and_unknown_ones_are_refused():
    assert KINDS["ares-ea"].drift_families() == D.ARES_FAMILIES
    with pytest.raises(ValueError, match="unknown ARES family"):
        KINDS["ares-ea"].drift_machine(family="nope", trial=0)


def test_machines_are_deterministic_per_seed(trials):
    a, b = (D.ares_drift_machine(trials[3], "drift-step", 101) for _ in range(2))
    c = D.ares_drift_machine(trials[3], "drift-step", 102)
    for t in (0, 77, 150, 299):
        assert torch.equal(a.incoming_at(t), b.incoming_at(t))
    assert not torch.equal(a.incoming_at(77), c.incoming_at(77))
    for m in (a, b):
        m.set(torch.tensor([11.0, -9.0, 1e-4, 10.0, -1e-4], dtype=torch.float64))
    assert [a.read() for _ in range(3)] == [b.read() for _ in range(3)]


def test_linear_drift_magnitudes_as_documented(trials):
    for k in range(10):
        g = D.draw_gaps(trials[k], "beam-linear", 101)
        d = g.drift(D.DURATION)
        for p in ("mu_x", "mu_y"):
            assert 20e-6 - 1e-12 <= abs(float(d[I[p]])) <= 60e-6 + 1e-12
        for a in ("mu_xp", "mu_yp"):
            assert 2e-6 - 1e-15 <= abs(float(d[I[a]])) <= 6e-6 + 1e-15
        for s in ("sigma_x", "sigma_y"):
            assert abs(float(d[I[s]] / trials[k].incoming[I[s]])) <= 0.10 + 1e-12
        assert float(d[I["energy"]]) == 0.0


def test_walk_sd_per_reading_as_documented(trials):
    g = D.draw_gaps(trials[0], "beam-walk", 101)
    steps = torch.stack([g.drift(t) for t in range(2001)]).diff(dim=0)
    assert float(steps[:, I["mu_x"]].std()) == pytest.approx(D.WALK_POSITION_M, rel=0.08)
    assert float(steps[:, I["mu_yp"]].std()) == pytest.approx(D.WALK_ANGLE_RAD, rel=0.08)
    assert float(steps[:, I["sigma_x"]].abs().max()) == 0.0


def test_step_happens_at_the_stated_reading(trials):
    m = D.ares_drift_machine(trials[5], "laser-step", 101)
    jump = m.incoming_at(D.STEP_AT) - m.incoming_at(D.STEP_AT - 1)
    assert torch.equal(m.incoming_at(D.STEP_AT - 1), trials[5].incoming)
    size = float(jump[[I["mu_x"], I["mu_y"]]].norm())
    assert 50e-6 - 1e-12 <= size <= 150e-6 + 1e-12
    mae = []
    for _ in range(D.STEP_AT + 2):  # knobs never move: only the step changes the beam
        m.read()
        mae.append(D.true_mae(m))
    assert len(set(mae[: D.STEP_AT])) == 1
    assert mae[D.STEP_AT] != mae[D.STEP_AT - 1] and mae[D.STEP_AT] == mae[D.STEP_AT + 1]


def test_hysteresis_same_setpoint_different_history(trials):
    w = D.PLAY_WIDTH[0]
    start = torch.tensor([10.0, -10.0, 0.0, 10.0, 0.0], dtype=torch.float64)
    target = start.clone()
    target[0] = 11.0
    beams = []
    for via in (12.0, 9.0):  # from above, from below
        m = D.ares_drift_machine(trials[2], "hysteresis", 101)
        pre = start.clone()
        pre[0] = via
        m.set(pre)
        m.set(target)
        assert torch.equal(m.get(), target)
        acting = float(m.hysteresis.y[0])
        assert acting == pytest.approx(11.0 + w if via > 11 else 11.0 - w)
        m.read()
        beams.append(m.last_true_observables)
    assert float((beams[0] - beams[1]).abs().max()) > 1e-7  # > 0.1 um apart
    none = D.ares_drift_machine(trials[2], "none", 101)
    none.set(target)
    assert torch.equal(none.hysteresis.y, target)


def test_static_gaps_as_documented(trials):
    g = D.draw_gaps(trials[4], "static", 101)
    assert all(1e-3 - 1e-12 <= abs(float(t)) <= 4e-3 + 1e-12 for t in g.tilt)
    M = g.corrector
    assert abs(float(M[0, 0]) - 1) <= 0.05 and abs(float(M[1, 1]) - 1) <= 0.05
    assert 0 < abs(float(M[0, 1])) <= 0.03 and 0 < abs(float(M[1, 0])) <= 0.03
    assert g.drift is None and float(g.play.abs().max()) == 0.0
    seg = D.GapSegment(g)
    x = torch.tensor([10.0, -20.0, 1e-3, 30.0, -2e-3], dtype=torch.float64)
    a = seg.acting_knobs(x)
    q = g.quad_steerer
    assert float(a[2]) == pytest.approx(float(M[0, 0] * 1e-3 + M[0, 1] * -2e-3 + q[0] * -20))
    assert float(a[4]) == pytest.approx(float(M[1, 1] * -2e-3 + M[1, 0] * 1e-3 + q[1] * 30))
    assert torch.equal(a[[0, 1, 3]], x[[0, 1, 3]])


def test_screen_blur_and_jitter_are_in_the_reading_not_the_true_beam(trials):
    m = D.ares_drift_machine(trials[1], "screen-jitter", 101)
    quiet = D.ares_drift_machine(trials[1], "none", 101)
    m.read()
    quiet.read()
    assert torch.equal(m.last_true_observables, quiet.last_true_observables)
    true, read = m.last_true_observables, m.last_observables
    assert not torch.equal(read, true)
    # sizes: blurred by the resolution, plus jitter of a few um at most
    blurred = torch.sqrt(true[[1, 3]] ** 2 + D.SCREEN_RESOLUTION_M**2)
    assert float((read[[1, 3]] - blurred).abs().max()) < 30e-6


def test_true_mae_closed_form(trials):
    m = D.ares_drift_machine(trials[0], "none", 101)
    with pytest.raises(ValueError):
        D.true_mae(m)
    m.read()
    m.last_true_observables = m.target + torch.tensor([1e-6, -2e-6, 3e-6, -6e-6]).double()
    assert D.true_mae(m) == pytest.approx(3e-6)


class TestAresStaticGapKind(MachineKindContract):
    """The model of a static-gap machine (rolled quads, corrector map) passes the contract."""

    kind_name = "ares-ea"
    model_options: ClassVar[dict] = {"trial": 3, "family": "static", "seed": 101}
    noise = 5e-6
    prior_options: ClassVar[dict] = {"n_starts": 1, "n_samples": 16}
