"""Faults found by an outside audit that the other fault tests do not cover, over real Channel
Access and judged by the IOC's own put log: a glitch of the objective during the best-point
confirmation of ``restore: best``.
"""

from __future__ import annotations

import pytest
import torch

from pigp_torch import cli
from pigp_torch.runlog import read_log
from tests.epics.test_faults_over_ca import (
    fault_at_read,
    final_setpoints,
    run,
    start_of,
    worst_step,
    write_config,
)


@pytest.fixture(autouse=True)
def private_locks(tmp_path, monkeypatch):
    monkeypatch.setenv("PIGP_LOCK_DIR", str(tmp_path / "locks"))


@pytest.fixture
def with_optimize(monkeypatch):
    modules = tuple(dict.fromkeys((*cli.COMMAND_MODULES, "optimize")))
    monkeypatch.setattr(cli, "COMMAND_MODULES", modules)


@pytest.mark.slow  # a 5-evaluation run with ramps and a restore: ~10-20 s on a busy host
def test_a_glitch_during_the_best_confirmation_restores_the_initial_setpoints(
    ioc, probe, ring, tmp_path, capsys, with_optimize
):
    """Every objective read after the last evaluation returns 1e30 (the glitch starts while the
    best point is being confirmed): the confirmation readings are discarded as outside the PV's
    range, the best is NOT confirmed, and the knobs go back exactly to the initial setpoints,
    every put within max_step; no evaluation is a glitch."""
    budget = 5
    probe.write_many(ioc.setpoint_pvs[:2], start_of(ring))
    mark = ioc.n_puts()
    config = write_config(tmp_path, ioc, ring, restore="best", objective_noise=0.04, budget=budget)
    with fault_at_read(budget + 1, lambda: probe.write(ioc.glitch_readings_pv, 50)):
        with pytest.warns(UserWarning, match="restoring the initial knobs instead"):
            code, captured = run(config, capsys)
    assert code == 0, captured.err
    log = read_log(tmp_path / "run.jsonl")
    assert log.n_evaluations == budget and float(log.Y().max()) < 5.0
    assert log.discarded, "the glitched confirmation readings were not logged as discarded"
    assert all(d["y"] == 1e30 for d in log.discarded)
    assert all(d["reason"].startswith("confirming the best point:") for d in log.discarded)
    end = log.last_end
    assert end["best_confirmation"]["confirmed"] is False
    assert end["restored_to"] == "initial (best not confirmed)" and end["restored"] is True
    assert final_setpoints(ioc, mark) == start_of(ring).tolist()  # the IOC's last puts
    assert torch.equal(probe.read_many(ioc.setpoint_pvs[:2]), start_of(ring))
    assert worst_step(ioc, mark) <= 1 + 1e-9
