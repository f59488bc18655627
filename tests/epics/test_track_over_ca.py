"""Track mode over real Channel Access (the shared simulated IOC on 127.0.0.1), judged by what the
IOC received (its put log) and holds: a glitch in a track run is never its estimate, a stop by
SIGTERM leaves the knobs at the estimate (exit 143), the time limit ends the run at the
estimate (exit 0). The faults that end a run (stuck supply, full disk, alarm severity, a stalled
or restarted IOC, an edited log) run in both modes in their own files (the ``run_mode``
fixture); the soak of 10,000 readings is in test_track_soak_over_ca.py.
"""

from __future__ import annotations

import os
import signal

import pytest
import torch

from pigp_torch.data.runlog import read_log

from .ca_runs import KNOBS, private_locks, start_of, with_optimize, write_config  # noqa: F401
from .test_faults_over_ca import fault_at_read, run, worst_step
from .test_faults_over_ca import final_setpoints as held

pytestmark = pytest.mark.usefixtures("private_locks", "with_optimize")  # from ca_runs

TRACK = {"mode": "track", "time_limit": "10 min"}


def best_x(log) -> list[float]:
    return max(log.evaluations, key=lambda e: e["y"])["x"]


def test_a_glitch_in_a_track_run_is_never_its_estimate(ioc, probe, ring, tmp_path, capsys):
    """The objective PV returns 1e30 on two reads in a row: both are discarded (outside the
    PV's range), and at the end the IOC holds the estimate (Nelder–Mead's best reading, not
    the glitch), reached by puts within max_step."""
    probe.write_many(ioc.setpoint_pvs[:2], start_of(ring))
    mark = ioc.n_puts()
    config = write_config(tmp_path, ioc, ring, budget=8, objective_noise=0.04, **TRACK)
    with fault_at_read(4, lambda: probe.write(ioc.glitch_readings_pv, 2)):
        code, captured = run(config, capsys)
    assert code == 0, captured.err
    log = read_log(tmp_path / "run.jsonl")
    assert [d["y"] for d in log.discarded] == [1e30, 1e30]
    end = log.last_end
    assert end["restored_to"] == "estimate" and end["reason"] == "max_readings (8) made"
    assert float(log.Y().max()) < 5.0
    assert held(ioc, mark) == best_x(log) == end["restore_target"] == end["final_setpoints"]
    assert worst_step(ioc, mark) <= 1 + 1e-9  # max_step 0.2 of the half-range (15 A)


def test_sigterm_ends_a_track_run_at_its_estimate(ioc, probe, ring, tmp_path, capsys):
    """SIGTERM at the 6th read of a run meant to go on for 10 min (the 5th evaluation: the
    first takes two reads with the noise stated): exit 143, the end record says interrupted,
    and the IOC holds the estimate (the best reading's setting)."""
    probe.write_many(ioc.setpoint_pvs[:2], start_of(ring))
    mark = ioc.n_puts()
    config = write_config(tmp_path, ioc, ring, budget=1000, objective_noise=0.04, **TRACK)
    with fault_at_read(6, lambda: os.kill(os.getpid(), signal.SIGTERM)):
        code, captured = run(config, capsys)
    assert code == 143, captured.err
    log = read_log(tmp_path / "run.jsonl")
    end = log.last_end
    assert end["status"] == "interrupted" and end["restored_to"] == "estimate"
    assert end["restored"] is True and log.n_evaluations == 4
    assert held(ioc, mark) == best_x(log)
    assert torch.equal(probe.read_many(ioc.setpoint_pvs[:2]), torch.tensor(best_x(log)))


def test_the_time_limit_ends_a_track_run_over_ca(ioc, probe, ring, tmp_path, capsys):
    """time_limit 2 s with room for 10,000 readings: the run ends on the clock (exit 0), with
    the readings' wall-clock times in the log and the IOC at the estimate."""
    probe.write_many(ioc.setpoint_pvs[:2], start_of(ring))
    mark = ioc.n_puts()
    config = write_config(tmp_path, ioc, ring, budget=10_000, mode="track", time_limit="2 s")
    code, captured = run(config, capsys)
    assert code == 0, captured.err
    log = read_log(tmp_path / "run.jsonl")
    end = log.last_end
    assert "the time limit of 2 s passed" in end["reason"] and log.n_evaluations >= 2
    t = [e["t_read"] for e in log.evaluations]
    assert t == sorted(t) and t[-1] - t[0] < 2.0 + 5.0  # the last step started within 2 s
    assert held(ioc, mark) == best_x(log)
