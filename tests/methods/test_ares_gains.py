"""The ARES model's fitted quadrupole gains: the row-wise Jacobian and the fit of a wrong
calibration."""

from __future__ import annotations

import pytest
import torch

pytest.importorskip("cheetah")

from pigp_torch.machines.ares_ea.cases import case_machine_parts
from pigp_torch.machines.ares_ea.methods import ares_model_parts
from pigp_torch.machines.ares_ea.simulation import knob_bounds, load_trials
from pigp_torch.optimizers._least_squares import fit_unknowns, row_jacobian

D = torch.float64


def _settings(n: int, seed: int, scale: float = 0.3) -> torch.Tensor:
    b = knob_bounds()
    Z = torch.rand(n, 5, generator=torch.Generator().manual_seed(seed), dtype=D)
    return scale * (b[0] + (b[1] - b[0]) * Z)  # moderate strengths: the beam stays on screen


def test_row_jacobian_matches_forward_mode_and_finite_differences():
    """Without gains the row-wise reverse-mode Jacobian equals torch's forward-mode Jacobian (to
    1e-10 relative); with gains (where forward mode fails on Cheetah's complex square root of
    k1) its gain columns equal central differences of the model (step 1e-6)."""
    X = _settings(7, 0)
    model16, c16, h16 = ares_model_parts(quad_gain_half_width=0)
    theta16 = c16 + 0.4 * h16
    J = torch.autograd.functional.jacobian(
        lambda t: model16(X, t), theta16, strategy="forward-mode", vectorize=True
    )
    R = row_jacobian(model16, X, theta16)
    assert R.shape == (7, 4, 16)
    assert float((R - J).abs().max()) <= 1e-10 * float(J.abs().max())

    model, _, _ = ares_model_parts()
    gains = torch.tensor([1.03, 0.97, 1.05], dtype=D)
    theta = torch.cat([theta16, gains])
    R = row_jacobian(model, X, theta)
    assert R.shape == (7, 4, 19)
    # the first 16 columns: the model without gains at the settings the magnets act with
    Xg = X * torch.stack(
        [gains[0], gains[1], torch.tensor(1.0, dtype=D), gains[2], torch.tensor(1.0, dtype=D)]
    )
    Jg = torch.autograd.functional.jacobian(
        lambda t: model16(Xg, t), theta16, strategy="forward-mode", vectorize=True
    )
    torch.testing.assert_close(R[..., :16], Jg, rtol=1e-9, atol=1e-12 * float(Jg.abs().max()))
    eps = 1e-6
    for k in range(16, 19):
        e = torch.zeros(19, dtype=D)
        e[k] = eps
        fd = (model(X, theta + e) - model(X, theta - e)) / (2 * eps)
        torch.testing.assert_close(R[..., k], fd, rtol=1e-5, atol=1e-9)
        assert float(fd.abs().max()) > 1e-5  # a gain moves the beam by > 10 nm per 1 %


def test_fit_recovers_quadrupoles_ten_percent_strong():
    """Readings of the quad-cal-10 machine (quadrupoles act with 1.10 k1) at 12 settings,
    noise-free: the fit with gains finds all three gains within 0.5 % of 1.10 (twice the
    prior's half width of 5 %) and explains the readings to 1 um (0.43 um: the prior still pulls the
    gains a little), the fit without gains leaves residuals above 100 um (313 um)."""
    trial = load_trials()[4]
    t, seg = case_machine_parts(trial, "quad-cal-10")
    X = _settings(12, 1)
    O = seg.observe(X, t.incoming, t.misalignments)
    model, c, h = ares_model_parts()
    u, _ = fit_unknowns(model, X, O, c, h, obs_sd=1e-6, prior_sd=3**-0.5, max_iter=100)
    gains = (c + h * u)[16:]
    torch.testing.assert_close(gains, torch.full((3,), 1.10, dtype=D), rtol=0, atol=5e-3)
    assert float((model(X, c + h * u) - O).abs().max()) < 1e-6

    model16, c16, h16 = ares_model_parts(quad_gain_half_width=0)
    u16, _ = fit_unknowns(model16, X, O, c16, h16, obs_sd=1e-6, prior_sd=3**-0.5, max_iter=100)
    assert float((model16(X, c16 + h16 * u16) - O).abs().max()) > 100e-6


def test_the_screen_resolution_unknown_blurs_the_sizes_only():
    """``screen_resolution`` > 0 adds one unknown r in [0, r_max] (centre and half width r_max/2):
    at r = 0 the model is the model without it to the bit; at r the sizes read are
    sqrt(sigma^2 + r^2) and the centroids unchanged, for one theta and a batch of thetas; the
    machine model names it with its unit."""
    from pigp_torch.machines.ares_ea.methods import ares_machine_model

    X = _settings(3, 1)
    model, c, h = ares_model_parts()
    model_r, c_r, h_r = ares_model_parts(screen_resolution=4e-5)
    assert c_r.shape == (20,) and float(c_r[-1]) == float(h_r[-1]) == 2e-5
    assert torch.equal(c_r[:19], c) and torch.equal(h_r[:19], h)
    theta = torch.cat([c, torch.zeros(1, dtype=D)])
    assert torch.equal(model_r(X, theta), model(X, c))
    theta[-1] = 1.5e-5
    o, o0 = model_r(X, theta), model(X, c)
    assert torch.equal(o[:, [0, 2]], o0[:, [0, 2]])
    torch.testing.assert_close(o[:, [1, 3]], (o0[:, [1, 3]].square() + 1.5e-5**2).sqrt())
    batch = torch.stack([theta, theta])[:, None, :]
    assert torch.equal(model_r(X, batch)[1], o)
    mm = ares_machine_model(torch.zeros(4), screen_resolution=4e-5)
    assert mm.unknown_names[-1] == "screen_resolution" and mm.unknown_units[-1] == "m"
    assert mm.unknown_names[-2] == "AREAMQZM3_gain"


def test_the_goal_of_a_model_with_a_resolution_is_on_the_beam():
    """The machine model with ``screen_resolution`` names a ``beam``: the sizes read, deblurred
    with the fitted r, are the model's sizes without r (the centroids untouched), so the goal
    (``goal_at``) is the MAE of the beam, not of the blurred reading; without it there is none."""
    from pigp_torch.machines.ares_ea.methods import ares_machine_model

    X = _settings(4, 2)
    model, c, _ = ares_model_parts()
    target = torch.tensor([1e-4, 3e-5, -2e-4, 4e-5], dtype=D)
    mm = ares_machine_model(target, screen_resolution=4e-5)
    assert ares_machine_model(target).beam is None
    theta = torch.cat([c, torch.tensor([1.5e-5], dtype=D)])
    beam = mm.beam(mm.observe(X, theta), theta)
    torch.testing.assert_close(beam, model(X, c), rtol=1e-10, atol=1e-15)
    torch.testing.assert_close(mm.goal_at(X, theta), mm.goal(model(X, c)), rtol=1e-10, atol=0)
    assert bool((mm.goal(mm.observe(X, theta)) != mm.goal_at(X, theta)).all())
