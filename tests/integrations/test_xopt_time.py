"""Xopt's time-dependent UCB on the reading clock (xopt-tdbo) on a drifting ARES-EA machine."""

from __future__ import annotations

import pytest
import torch

pytest.importorskip("xopt")

from pigp_torch.integrations.xopt_time import ReadingClockTDUCB
from pigp_torch.machines import KINDS
from pigp_torch.machines.drift import drive
from pigp_torch.methods import METHODS, RunContext


def tdbo_run(readings: int, seed: int, **options):
    machine = KINDS["ares-ea"].drift_machine(family="drift", seed=101, trial=0, noise=0.0)
    ctx = RunContext(machine=machine, seed=seed, noise=None, maximize=machine.maximize)
    opt = METHODS["xopt-tdbo"].with_options(n_restarts=4, **options).build(ctx)
    X, _ = drive(machine, opt, readings, set_back=False)
    return machine, opt, X


def test_tdbo_runs_on_the_reading_clock_and_repeats_with_its_seed():
    machine, opt, X = tdbo_run(6, seed=3)
    gen = opt.generator
    assert isinstance(gen, ReadingClockTDUCB)
    assert gen.data["time"].tolist() == [0.0, 1.0, 2.0, 3.0, 4.0, 5.0]
    assert gen.target_prediction_time == 5.0  # the last ask was for reading 5 (after 0..4)
    assert gen.model.models[0].train_inputs[0].shape[-1] == machine.dim + 1  # knobs and time
    assert bool((X >= machine.bounds[0]).all() and (X <= machine.bounds[1]).all())
    assert len({tuple(x.tolist()) for x in X}) == 6  # it moves at every reading
    _, _, again = tdbo_run(6, seed=3)
    assert torch.equal(X, again)
    _, _, other = tdbo_run(6, seed=4)
    assert not torch.equal(X, other)


def test_forgetting_time_keeps_the_recent_readings_only():
    _, opt, _ = tdbo_run(5, seed=0, forgetting_time=2.0)
    kept = opt.generator.get_training_data(opt.generator.data)
    assert kept["time"].tolist() == [3.0, 4.0]
