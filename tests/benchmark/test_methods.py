"""Tests of the benchmark's method builders that are not covered by the tiny benchmark table."""

import pytest
import torch

from pigp_torch.benchmark import METHODS, RunContext
from pigp_torch.machine import SimulatedMachine
from pigp_torch.models import PhysicsMean
from pigp_torch.simulation import Spear3Coupling

CHEAP_BO = {"num_restarts": 2, "raw_samples": 32}


def test_physics_mean_method_fits_the_mean_to_the_data(tiny_prior):
    """After 3 readings the fitted mean is closer to them than the prior mean and stays bounded."""
    sim = Spear3Coupling(1)
    machine = SimulatedMachine(sim, noise=0.04, seed=1)
    ctx = RunContext(machine=machine, prior=tiny_prior, seed=5)
    opt = METHODS["pigp-physics-mean"].with_options(**CHEAP_BO).build(ctx)
    X = torch.zeros(3, sim.dim, dtype=torch.float64)
    X[1, 0], X[2, 1] = 0.004, -0.004
    Y = sim.loss_rate(X).detach()
    for x, y in zip(X, Y, strict=True):
        opt.tell(x, float(y))
    x_new = opt.ask()
    mean = opt.last_model.mean_module
    assert isinstance(mean, PhysicsMean)
    start = PhysicsMean.from_prior(tiny_prior, center=torch.zeros(sim.dim, dtype=torch.float64))
    with torch.no_grad():
        err_fit = (mean(X) - Y).abs().max()
        err_start = (start(X) - Y).abs().max()
    assert float(err_fit) < 0.5 * float(err_start)
    box = opt.last_info
    assert bool((x_new >= box["trust_lower"]).all() and (x_new <= box["trust_upper"]).all())
    assert float(mean.center.abs().max()) < 3 * sim.knob_limit


def test_physics_mean_method_rejects_unknown_center_prior(tiny_prior):
    """An unknown center_prior raises ValueError."""
    machine = SimulatedMachine(Spear3Coupling(1), noise=0.04, seed=1)
    ctx = RunContext(machine=machine, prior=tiny_prior, seed=5)
    with pytest.raises(ValueError, match="center_prior"):
        METHODS["pigp-physics-mean"].with_options(center_prior="bad").build(ctx)
