"""The public names that moved into the ARES-EA kind's folder still import from their old paths,
as the same objects."""

from __future__ import annotations

import importlib

import pytest

MOVED = {
    "pigp_torch.machine.ares": "pigp_torch.machines.ares_ea.machine",
    "pigp_torch.benchmark.ares": "pigp_torch.machines.ares_ea.benchmark",
    "pigp_torch.simulation.ares": "pigp_torch.machines.ares_ea.simulation",
    "pigp_torch.commands.bench_ares": "pigp_torch.machines.ares_ea.command",
}


@pytest.mark.parametrize(("old", "new"), sorted(MOVED.items()))
def test_an_old_path_re_exports_the_moved_names(old, new):
    alias, module = importlib.import_module(old), importlib.import_module(new)
    assert alias.__all__
    for name in alias.__all__:
        assert getattr(alias, name) is getattr(module, name), name


def test_the_names_outside_checks_call_are_there():
    from pigp_torch.benchmark.ares import run_ares_benchmark, run_ares_trial, score_runs
    from pigp_torch.machine.ares import AresMachine
    from pigp_torch.methods import METHODS, RunContext

    assert AresMachine.__module__ == "pigp_torch.machines.ares_ea.machine"
    assert {"published-bo", "published-nm", "ares-physics"} <= set(METHODS)
    assert METHODS["ares-physics"].machine == "ares-ea"
    assert callable(run_ares_benchmark) and callable(run_ares_trial) and callable(score_runs)
    assert RunContext().seed == 0
