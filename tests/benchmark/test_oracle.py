"""The oracle reference: pigp-physics told the machine's own shape, background and peak."""

from __future__ import annotations

import math

import pytest
import torch

from pigp_torch.bench.oracle import ORACLE, oracle_prior
from pigp_torch.bench.protocol import benchmark_ring
from pigp_torch.machine import SimulatedMachine
from pigp_torch.methods import RunContext
from pigp_torch.simulation.ensemble import ensemble_optima
from pigp_torch.simulation.spec import SPEAR3


def test_oracle_prior_is_the_machines_own_peak(tiny_prior):
    """Background, peak height and shape are the machine's (not the model ring's), the shape
    and precision obey B = 2 c Sigma, and the centre prior stays the model's."""
    sim = benchmark_ring(3, SPEAR3)
    ctx = RunContext(machine=SimulatedMachine(sim, noise=0.04, seed=3), prior=tiny_prior, seed=0)
    prior = oracle_prior(ctx)
    opt = ensemble_optima([3], model=sim)
    assert prior.f_inf == pytest.approx(sim.loss_background, rel=1e-12)
    assert prior.f_inf != pytest.approx(tiny_prior.f_inf, rel=1e-3)  # machine 3's own map
    assert prior.f_x0 == pytest.approx(float(sim.loss_rate(opt.centers[0])), rel=1e-9)
    torch.testing.assert_close(prior.peak_shape, opt.shapes[0])
    c = (prior.f_x0 - prior.f_inf) ** -2
    torch.testing.assert_close(prior.peak_shape, 2 * c * prior.precision)
    assert prior.center_cov is tiny_prior.center_cov
    bo = ORACLE.build(ctx)
    assert bo.model.f_inf == prior.f_inf
    assert bo.model.log_c_model == pytest.approx(-2 * math.log(prior.f_x0 - prior.f_inf))
