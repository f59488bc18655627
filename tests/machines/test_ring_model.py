"""The ring as a machine model: what ``observe`` computes, its prior, its unknowns fitted."""

from __future__ import annotations

import pytest
import torch

from pigp_torch.machines import KINDS
from pigp_torch.optimizers._least_squares import fit_unknowns
from pigp_torch.prior import prior_from_model
from pigp_torch.prior.machine_model import prior_from_machine_model

D = torch.float64


@pytest.fixture(scope="module")
def ring():
    sim = KINDS["spear3"].simulator(error_seed=0)
    return sim, KINDS["spear3"].model(sim=sim)


def _settings(sim, n, seed=0):
    gen = torch.Generator().manual_seed(seed)
    return sim.bounds[1] * (torch.rand(n, sim.dim, generator=gen, dtype=D) - 0.5)


def test_observe_is_the_ring_moved_by_its_coupling_error_with_its_loss_map(ring):
    sim, model = ring
    K = sim.dim
    assert model.unknown_names[:2] == [f"{n}_error" for n in sim.knob_names[:2]]
    assert model.unknown_names[K:] == ["loss_background", "loss_scale"]
    assert model.knob_units == ["A"] * K and model.unknown_units[-2:] == ["1", "1"]
    X = _settings(sim, 3)
    delta = torch.linspace(-2.0, 2.0, K, dtype=D)
    theta = torch.cat([delta, torch.tensor([-0.2, 0.1], dtype=D)])
    with torch.no_grad():
        got = model.observe(X, theta)
        ref = sim.evaluate(X + delta)
    f_inf = sim.loss_rate_map[0]
    expected_loss = f_inf * 0.8 + 1.1 * (ref.loss_rate - f_inf)
    torch.testing.assert_close(got[:, 0], expected_loss, rtol=1e-12, atol=0.0)
    torch.testing.assert_close(got[:, 1], ref.eps_x * 1e9, rtol=1e-12, atol=0.0)
    torch.testing.assert_close(got[:, 2], ref.eps_y * 1e12, rtol=1e-12, atol=0.0)
    assert model.goal_background(theta) == pytest.approx(-f_inf * 0.8)


def test_the_ring_models_prior_is_the_benchmarks_prior_of_its_loss_rate(ring):
    """At the centre of the unknowns the machine model's prior (the generic chain) is the one the
    benchmark computes from the model ring's loss rate: the same optimum and precision."""
    sim, model = ring
    options = {"noise": 0.04, "n_starts": 2, "seed": 0, "n_samples": 64}
    generic = prior_from_machine_model(model, **options)
    direct = prior_from_model(sim.loss_rate, sim.bounds, f_inf=sim.loss_background, **options)
    assert generic.f_inf == pytest.approx(direct.f_inf, rel=1e-12)
    torch.testing.assert_close(generic.x0, direct.x0, rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(generic.precision, direct.precision, rtol=1e-5, atol=1e-12)


def test_the_online_fit_finds_the_rings_unknowns(ring):
    """The least-squares fit that ARES's method uses recovers a ring's coupling error and loss
    map from noise-free readings at 16 settings (the model at known unknowns)."""
    sim, model = ring
    K = sim.dim
    gen = torch.Generator().manual_seed(5)
    u_true = 0.6 * (2 * torch.rand(K + 2, generator=gen, dtype=D) - 1)
    theta_true = model.unknown_center + model.unknown_half_width * u_true
    X = _settings(sim, 16, seed=2)
    with torch.no_grad():
        O = model.observe(X, theta_true)
    c, h = model.unknown_center, model.unknown_half_width
    u, _ = fit_unknowns(model.observe, X, O, c, h, obs_sd=0.01, prior_sd=10.0, max_iter=15)
    err_before = float((c - theta_true).abs().max())
    err_after = float((c + h * u - theta_true).abs().max())
    assert err_after < 0.01 * err_before, (err_before, err_after)


def test_the_online_fit_and_prior_check_tune_a_ring_through_its_model(ring):
    """The optimizer of ARES-EA's ``ares-physics`` (the unknowns fitted online, the fitted
    model's optimum asked in a trust region, the prior check) runs on the ring's model: a ring
    whose coupling error and loss map it is not told (a ModelMachine of the model at those
    unknowns), read with noise, gains loss rate within 8 readings."""
    from pigp_torch.machine.model_machine import ModelMachine
    from pigp_torch.optimizers.model_check import CheckedModelOptimizer

    sim, model = ring
    theta = model.sample_unknowns(1, seed=11)[0]
    machine = ModelMachine(model, theta, noise=0.01, seed=0, maximize=True)
    opt = CheckedModelOptimizer.from_machine_model(model, obs_sd=0.01, seed=0, maximize=True)
    start = float(-model.goal(machine.true_observables(machine.get())))
    for _ in range(8):
        y = machine.read()
        opt.tell(machine.get(), y, observables=machine.last_observables)
        machine.set(opt.ask())
    best = float(-model.goal(machine.true_observables(opt.best()[0])))
    x_model, _ = sim.optimum()  # the model ring's optimum; the machine's lies delta away
    x_machine = torch.clamp(x_model - theta[: sim.dim], sim.bounds[0], sim.bounds[1])
    optimum = float(-model.goal(machine.true_observables(x_machine)))
    assert best > start + 0.5 * (optimum - start), (start, best, optimum)
