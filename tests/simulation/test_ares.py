"""The ARES-EA segment in Cheetah against closed-form optics, the trials loader, batching."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

pytest.importorskip("cheetah")

from pigp_torch.machines.ares_ea.simulation import (
    INCOMING_NAMES,
    KNOB_NAMES,
    START_SETTING,
    AresSegment,
    knob_bounds,
    load_lattice,
    load_trials,
    parse_trial_ids,
)

D = torch.float64


@pytest.fixture(scope="module")
def seg():
    return AresSegment()


@pytest.fixture(scope="module")
def trials():
    return load_trials()


def _beam(mu_x=0.0, mu_xp=0.0, mu_y=0.0, mu_yp=0.0, sx=1e-4, sxp=1e-5, sy=2e-4, syp=2e-5):
    v = dict.fromkeys(INCOMING_NAMES, 0.0)
    v.update(energy=1e8, mu_x=mu_x, mu_xp=mu_xp, mu_y=mu_y, mu_yp=mu_yp, sigma_x=sx)
    v.update(sigma_xp=sxp, sigma_y=sy, sigma_yp=syp, sigma_s=1e-5, sigma_p=1e-4)
    return torch.tensor([v[n] for n in INCOMING_NAMES], dtype=D)


def _drift(L):
    return np.array([[1.0, L], [0.0, 1.0]])


def _quad(k, L):
    """Thick quadrupole, one plane, strength k (1/m²; k > 0 focusing in this plane)."""
    if k > 0:
        w = math.sqrt(k)
        return np.array(
            [[math.cos(w * L), math.sin(w * L) / w], [-w * math.sin(w * L), math.cos(w * L)]]
        )
    if k < 0:
        w = math.sqrt(-k)
        return np.array(
            [[math.cosh(w * L), math.sinh(w * L) / w], [w * math.sinh(w * L), math.cosh(w * L)]]
        )
    return _drift(L)


def _element_map(seg, name, energy=1e8):
    import cheetah

    el = seg._el[name]
    # Cheetah caches the map under the id() and version of the element's tensors; a tensor set
    # by the test may reuse a freed one's id (as AresSegment's own calls, drop the cache)
    el.__dict__.pop("_cache", None)
    R = el.first_order_transfer_map(torch.tensor(energy, dtype=D), cheetah.Species("electron"))
    return R.detach().numpy()


def test_drift_matches_closed_form(seg):
    """A drift of the lattice moves x by L x' (and y by L y') and nothing else transversely."""
    L = load_lattice()["elements"][1]["length"]
    R = _element_map(seg, "Drift_AREASOLA1")
    np.testing.assert_allclose(R[0:2, 0:2], _drift(L), rtol=0, atol=1e-15)
    np.testing.assert_allclose(R[2:4, 2:4], _drift(L), rtol=0, atol=1e-15)
    np.testing.assert_allclose(R[0:2, 2:4], 0.0, atol=0)


@pytest.mark.parametrize("k1", [25.0, -40.0, 72.0])
def test_thick_quadrupole_matches_closed_form(seg, k1):
    """A thick quadrupole focuses in x with cos/sin(√k L)/√k and defocuses in y with
    cosh/sinh (and the other way round for k < 0)."""
    q = seg._el["AREAMQZM1"]
    L = float(q.length)
    old = q.k1
    q.k1 = torch.tensor(k1, dtype=D)
    try:
        R = _element_map(seg, "AREAMQZM1")
    finally:
        q.k1 = old
    np.testing.assert_allclose(R[0:2, 0:2], _quad(k1, L), rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(R[2:4, 2:4], _quad(-k1, L), rtol=1e-12, atol=1e-14)


def _hand_segment(k, incoming_mu, misalign):
    """Centroid and 4x4 transfer matrix of the whole segment by hand (per plane)."""
    lat = load_lattice()["elements"]
    k1 = {"AREAMQZM1": k[0], "AREAMQZM2": k[1], "AREAMQZM3": k[3]}
    kick = {"AREAMCVM1": (0.0, k[2]), "AREAMCHM1": (k[4], 0.0)}
    mis = {"AREAMQZM1": misalign[0:2], "AREAMQZM2": misalign[2:4], "AREAMQZM3": misalign[4:6]}
    Mx, My = np.eye(2), np.eye(2)
    cx, cy = np.array(incoming_mu[0:2]), np.array(incoming_mu[2:4])
    for e in lat:
        if e["type"] == "Drift":
            A = B = _drift(e["length"])
            cx, cy = A @ cx, B @ cy
        elif e["type"] == "Quadrupole":
            A, B = _quad(k1[e["name"]], e["length"]), _quad(-k1[e["name"]], e["length"])
            dx, dy = np.array([mis[e["name"]][0], 0.0]), np.array([mis[e["name"]][1], 0.0])
            cx, cy = A @ (cx - dx) + dx, B @ (cy - dy) + dy
        elif e["type"].endswith("Corrector"):
            A = B = _drift(e["length"])
            hx, hy = kick[e["name"]]
            cx, cy = A @ cx + np.array([0.0, hx]), B @ cy + np.array([0.0, hy])
        else:
            continue
        Mx, My = A @ Mx, B @ My
    return cx, cy, Mx, My


def test_segment_matches_hand_computed_optics(seg):
    """The whole segment (drifts, three misaligned thick quadrupoles, two correctors, a misaligned
    screen) gives the centroid and rms sizes of the hand-computed 2x2 matrices per plane."""
    k = [12.0, -20.0, 1.5e-3, 9.0, -2.0e-3]
    mis = [1e-4, -2e-4, 3e-4, 5e-5, -4e-4, 2e-4, 1e-4, -3e-4]
    mu = [2e-4, -3e-5, -1e-4, 4e-5]
    sx, sxp, sy, syp = 1e-4, 1e-5, 2e-4, 2e-5
    inc = _beam(*mu, sx=sx, sxp=sxp, sy=sy, syp=syp)
    obs = seg.observe(torch.tensor(k, dtype=D), inc, torch.tensor(mis, dtype=D)).numpy()
    cx, cy, Mx, My = _hand_segment(k, mu, mis)
    sig_x = math.sqrt(Mx[0, 0] ** 2 * sx**2 + Mx[0, 1] ** 2 * sxp**2)
    sig_y = math.sqrt(My[0, 0] ** 2 * sy**2 + My[0, 1] ** 2 * syp**2)
    expected = [cx[0] - mis[6], sig_x, cy[0] - mis[7], sig_y]
    np.testing.assert_allclose(obs, expected, rtol=1e-10, atol=1e-15)


def test_misaligned_quadrupole_kick_closed_form(seg):
    """A beam on axis through a quadrupole offset by d leaves it at x = (1 - cos √k L) d,
    x' = √k sin(√k L) d; downstream the drifts carry it to the screen."""
    k1, d = 30.0, 3e-4
    mis = torch.zeros(8, dtype=D)
    mis[0] = d  # Q1 offset in x
    k = torch.tensor([k1, 0.0, 0.0, 0.0, 0.0], dtype=D)
    obs = seg.observe(k, _beam(), mis)
    lat = load_lattice()["elements"]
    L = lat[2]["length"]
    w = math.sqrt(k1)
    x, xp = (1 - math.cos(w * L)) * d, w * math.sin(w * L) * d
    downstream = sum(e.get("length", 0.0) for e in lat[3:])
    assert float(obs[0]) == pytest.approx(x + xp * downstream, rel=1e-10)
    assert abs(float(obs[2])) < 1e-18  # the offset is horizontal only


def test_batched_equals_loop(seg, trials):
    """A batch of settings gives the same four numbers as one call per setting."""
    t = trials[7]
    gen = torch.Generator().manual_seed(0)
    b = knob_bounds()
    X = b[0] + (b[1] - b[0]) * torch.rand(6, 5, generator=gen, dtype=D)
    batched = seg.observe(X, t.incoming, t.misalignments)
    looped = torch.stack([seg.observe(x, t.incoming, t.misalignments) for x in X])
    assert batched.shape == (6, 4)
    torch.testing.assert_close(batched, looped, rtol=1e-12, atol=1e-18)


def test_batched_unknowns_equal_loop(seg, trials):
    """A batch of unknowns (50 incoming beams and misalignments, the screen's included) at one
    setting gives the same four numbers as one call per draw; the screen's offset moves the read
    centroid by exactly its size."""
    t = trials[4]
    gen = torch.Generator().manual_seed(1)
    inc = t.incoming * (1 + 0.2 * torch.rand(50, 11, generator=gen, dtype=D))
    mis = 5e-4 * (2 * torch.rand(50, 8, generator=gen, dtype=D) - 1)
    x = torch.tensor(START_SETTING, dtype=D)
    batched = seg.observe(x, inc, mis)
    looped = torch.stack([seg.observe(x, i, m) for i, m in zip(inc, mis, strict=True)])
    assert batched.shape == (50, 4)
    torch.testing.assert_close(batched, looped, rtol=1e-12, atol=1e-18)
    shifted = mis.clone()
    shifted[:, 6:8] += 1e-4
    diff = seg.observe(x, inc, shifted) - batched
    torch.testing.assert_close(diff[:, [0, 2]], torch.full((50, 2), -1e-4, dtype=D))
    assert float(diff[:, [1, 3]].abs().max()) == 0.0


def test_observe_is_differentiable(seg, trials):
    """Autograd gradients of the four numbers in the knobs match central differences."""
    t = trials[3]
    x0 = torch.tensor(START_SETTING, dtype=D) + torch.tensor([1.0, -2.0, 1e-4, 3.0, -2e-4])

    def f(x):
        return seg.observe(x, t.incoming, t.misalignments)

    jac = torch.autograd.functional.jacobian(f, x0)
    h = torch.tensor([1e-4, 1e-4, 1e-8, 1e-4, 1e-8], dtype=D)
    for i in range(5):
        e = torch.zeros(5, dtype=D)
        e[i] = h[i]
        fd = (f(x0 + e) - f(x0 - e)) / (2 * h[i])
        torch.testing.assert_close(jac[:, i], fd, rtol=1e-5, atol=1e-9)


def test_trials_loader(trials):
    """The shipped trials 0-149 load: targets, beams, misalignments, initial magnets."""
    assert sorted(trials) == list(range(150))
    t = trials[50]
    assert t.target.shape == (4,) and t.incoming.shape == (11,) and t.misalignments.shape == (8,)
    assert float(t.target[0]) == pytest.approx(0.0003893377142958343)
    assert float(t.target[2]) == pytest.approx(-0.0019807142671197653)  # mu_y is the 3rd entry
    rng = load_lattice()["incoming_beam_ranges"]
    for tr in trials.values():
        assert (tr.misalignments.abs() <= 5e-4).all()
        lo, hi = torch.tensor(rng["low"], dtype=D), torch.tensor(rng["high"], dtype=D)
        assert ((tr.incoming >= lo) & (tr.incoming <= hi)).all()
        assert tr.initial is not None and tr.initial.shape == (5,)


def test_trials_loader_errors(tmp_path):
    """A file with non-integer keys or a missing field is refused with a one-line error."""
    p = tmp_path / "t.yaml"
    p.write_text("a: {target: {}, incoming: {}, misalignments: {}}\n")
    with pytest.raises(ValueError, match="integers"):
        load_trials(p)
    p.write_text("0: {target: {mu_x: 0}, incoming: {}, misalignments: {}}\n")
    with pytest.raises(ValueError, match="target lacks"):
        load_trials(p)
    with pytest.raises(FileNotFoundError):
        load_trials(tmp_path / "none.yaml")


def test_parse_trial_ids():
    """Ranges are inclusive, lists keep their order, duplicates go, bad text is refused."""
    assert parse_trial_ids("50-52") == [50, 51, 52]
    assert parse_trial_ids("7, 3,5-6,3") == [7, 3, 5, 6]
    assert len(parse_trial_ids("50-149")) == 100
    for bad in ("", "5-", "a", "9-3", "1,,2"):
        with pytest.raises(ValueError):
            parse_trial_ids(bad)


def test_knob_bounds():
    """Unidirectional bounds keep Q1, Q3 focusing and Q2 defocusing (in x)."""
    b = knob_bounds(unidirectional=True)
    assert b[0, 0] == 0 and b[1, 1] == 0 and b[0, 3] == 0
    assert len(KNOB_NAMES) == b.shape[1] == 5
    assert float(knob_bounds()[1, 2]) == pytest.approx(6.1782e-3)
