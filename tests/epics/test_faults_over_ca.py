"""Faults injected into the simulated IOC over real Channel Access, judged by what the IOC
received: a glitch of the objective, a readback offset, a stuck readback. Every check of where
the knobs went reads the IOC's own put log (every put it accepted, with the setpoint before
it), not the client's account.

Runs go through `pigp optimize` in this process; a fault is armed at the n-th objective read
of the run (a patched ``EpicsMachine.read`` writes the IOC's switch first).
"""

from __future__ import annotations

import contextlib

import pytest
import torch
import yaml

from pigp_torch import cli
from pigp_torch.data.runlog import read_log
from pigp_torch.machine.epics import EpicsMachine

KNOBS = ["01G-QSS4", "02G-QSS3"]
MAX_STEP = 0.2  # of the half-range (15 A): 3 A


@pytest.fixture(autouse=True)
def private_locks(tmp_path, monkeypatch):
    monkeypatch.setenv("PIGP_LOCK_DIR", str(tmp_path / "locks"))


@pytest.fixture
def with_optimize(monkeypatch):
    modules = tuple(dict.fromkeys((*cli.COMMAND_MODULES, "optimize")))
    monkeypatch.setattr(cli, "COMMAND_MODULES", modules)


def bounds_of(ring) -> torch.Tensor:
    idx = [list(ring.knob_names).index(n) for n in KNOBS]
    return ring.bounds[:, idx] / 2


def start_of(ring) -> torch.Tensor:
    """2.5 / -1.25 A: a nonzero start, so that a restore is visible."""
    return torch.tensor([2.5, -1.25], dtype=torch.float64)


def write_config(tmp_path, ioc, ring, **over) -> str:
    b = bounds_of(ring)
    data = {
        "machine": {"kind": "epics", "settle_time": 0.1, "timeout": 1.0, "stale_timeout": 1.0},
        "knobs": {k: [float(b[0, i]), float(b[1, i])] for i, k in enumerate(KNOBS)},
        "objective": {"pv": ioc.loss_rate_pv},
        "method": {"name": "nelder-mead", "options": {"initial_simplex_size": 0.5}},
        "budget": 8,
        "max_step": MAX_STEP,
        "log": "run.jsonl",
        "retry_interval": 0.05,
        "restore_interval": 0.1,
        "restore_attempts": 2,
    }
    data.update(over)
    path = tmp_path / "run.yaml"
    path.write_text(yaml.safe_dump(data))
    return str(path)


@contextlib.contextmanager
def fault_at_read(n: int, arm):
    """``arm()`` runs just before the ``n``-th objective read of the run (1-based)."""
    calls = {"n": 0}
    real = EpicsMachine.read

    def read(self):
        calls["n"] += 1
        if calls["n"] == n:
            arm()
        return real(self)

    EpicsMachine.read = read
    try:
        yield calls
    finally:
        EpicsMachine.read = real


def worst_step(ioc, since: int) -> float:
    """The largest |value - previous| of a put to the run's knobs the IOC accepted, in units of
    the step limit (3 A)."""
    puts = [p for p in ioc.puts(since) if p.get("knob") in KNOBS]
    assert puts, "the IOC received no put"
    limit = MAX_STEP * 15.0
    return max(abs(p["value"] - p["previous"]) for p in puts) / limit


def final_setpoints(ioc, since: int) -> list[float]:
    """Each knob's setpoint after the last put the IOC accepted for it."""
    last = {}
    for p in ioc.puts(since):
        if p.get("knob") in KNOBS:
            last[p["knob"]] = p["value"]
    return [last[k] for k in KNOBS]


def run(config, capsys):
    code = cli.main(["optimize", "--config", config, "--quiet"])
    return code, capsys.readouterr()


def test_a_huge_glitch_is_discarded_and_never_the_best(ioc, probe, ring, tmp_path, capsys,
                                                       with_optimize):  # fmt: skip
    """The objective PV returns 1e30 on two reads in a row (step 2; with the noise stated the
    first evaluation takes two reads): both are outside the PV's range (LOPR/HOPR 0..100
    mA/min), discarded and logged, and the third read is the evaluation; 1e30 is never an
    evaluation nor the best; with restore: best the best point is read again and confirmed
    before the knobs are left there (or, reading below the start, not); no put exceeds
    max_step."""
    probe.write_many(ioc.setpoint_pvs[:2], start_of(ring))
    mark = ioc.n_puts()
    config = write_config(tmp_path, ioc, ring, restore="best", objective_noise=0.04)
    with fault_at_read(4, lambda: probe.write(ioc.glitch_readings_pv, 2)):
        code, captured = run(config, capsys)
    assert code == 0, captured.err
    log = read_log(tmp_path / "run.jsonl")
    assert [d["y"] for d in log.discarded] == [1e30, 1e30]
    assert all("outside the objective range [0, 100]" in d["reason"] for d in log.discarded)
    assert log.n_evaluations == 8 and float(log.Y().max()) < 5.0
    assert log.evaluations[2]["reads"] == 3
    end = log.last_end
    conf = end["best_confirmation"]
    assert len(conf["readings"]) == 3
    if end["restored_to"] == "best (confirmed)":
        assert end["best"]["y"] < 5.0
        assert final_setpoints(ioc, mark) == end["best"]["x"]  # what the IOC holds
    else:  # a best no better than the start (by the noise) read below it again: not kept
        assert end["restored_to"] == "initial (best not confirmed)"
        assert conf["not_below_start"] is False and end["rejected_best"]["y"] < 5.0
        assert final_setpoints(ioc, mark) == start_of(ring).tolist()
    assert worst_step(ioc, mark) <= 1 + 1e-9


def test_a_glitch_inside_the_range_is_reread_and_discarded(ioc, probe, ring, tmp_path, capsys,
                                                           with_optimize):  # fmt: skip
    """With the noise stated (0.04 mA/min), a single reading of 50 mA/min (inside the PV's
    range) is far from the run's median: it is read again, the re-read does not agree, and the
    glitch is discarded (logged) and never the best."""
    probe.write_many(ioc.setpoint_pvs[:2], start_of(ring))
    probe.write(ioc.glitch_value_pv, 50.0)
    mark = ioc.n_puts()
    config = write_config(tmp_path, ioc, ring, objective_noise=0.04, budget=6)
    with fault_at_read(5, lambda: probe.write(ioc.glitch_readings_pv, 1)):
        code, captured = run(config, capsys)
    assert code == 0, captured.err
    log = read_log(tmp_path / "run.jsonl")
    assert [d["y"] for d in log.discarded] == [50.0]
    assert "not confirmed: the re-read" in log.discarded[0]["reason"]
    assert float(log.Y().max()) < 5.0 and log.last_end["best"]["y"] < 5.0
    assert torch.equal(probe.read_many(ioc.setpoint_pvs[:2]), start_of(ring))
    assert worst_step(ioc, mark) <= 1 + 1e-9


def test_a_repeated_glitch_is_caught_when_the_best_is_confirmed(ioc, probe, ring, tmp_path,
                                                                capsys, with_optimize):  # fmt: skip
    """A glitch of 50 mA/min that repeats on its re-read cannot be told from a real reading by
    readings alone: it becomes an evaluation. With restore: best the best point is read again
    at the end, does not reproduce, and the run says so, restores the initial setpoints and
    reports no best (the rejected one is named as such)."""
    probe.write_many(ioc.setpoint_pvs[:2], start_of(ring))
    probe.write(ioc.glitch_value_pv, 50.0)
    mark = ioc.n_puts()
    config = write_config(tmp_path, ioc, ring, objective_noise=0.04, budget=5, restore="best")
    with fault_at_read(5, lambda: probe.write(ioc.glitch_readings_pv, 2)):
        with pytest.warns(UserWarning, match="the best point did not reproduce"):
            code, captured = run(config, capsys)
    assert code == 0, captured.err
    end = read_log(tmp_path / "run.jsonl").last_end
    assert end["best"] is None and end["rejected_best"]["y"] == 50.0
    assert end["control_reading"]["confirmed"] is True
    assert end["best_confirmation"]["confirmed"] is False
    assert "best: none (the best reading, y = 50 mA/min" in captured.out
    assert end["best_confirmation"]["mean"] < 5.0
    assert end["restored_to"] == "initial (best not confirmed)" and end["restored"] is True
    assert final_setpoints(ioc, mark) == start_of(ring).tolist()
    assert torch.equal(probe.read_many(ioc.setpoint_pvs[:2]), start_of(ring))
    assert worst_step(ioc, mark) <= 1 + 1e-9


@pytest.mark.parametrize("offset", [0.03, 0.1])
def test_a_readback_offset_leaves_the_setpoints_exact(ioc, probe, ring, tmp_path, capsys,
                                                      with_optimize, offset):  # fmt: skip
    """Every readback reads its setpoint + offset. 0.03 A (inside the readback tolerance of
    0.05 A): the run completes and the SETPOINTS end exactly where they were found. 0.1 A
    (outside): the first set (to the setpoints found: no put) fails its readback check, the run
    stops (exit 1) after zero evaluations and the setpoints are exactly where they were found,
    never put (the offset was there before the run)."""
    start = start_of(ring)
    probe.write_many(ioc.setpoint_pvs[:2], start)
    probe.write(ioc.readback_offset_pv, offset)
    mark = ioc.n_puts()
    machine = {"kind": "epics", "settle_time": 0.1, "timeout": 0.5, "stale_timeout": 1.0,
               "tolerance": 0.05}  # fmt: skip
    config = write_config(tmp_path, ioc, ring, machine=machine, readback_tolerance=0.002)
    code, captured = run(config, capsys)
    log = read_log(tmp_path / "run.jsonl")
    assert log.starts[0]["initial_knobs"] == start.tolist()  # setpoints, not readbacks
    assert log.starts[0]["found_readbacks"] == pytest.approx((start + offset).tolist())
    if offset < 0.05:
        assert code == 0, captured.err
        assert log.n_evaluations == 8
    else:
        assert code == 1, captured.err
        assert log.n_evaluations == 0 and "ReadbackError" in log.last_end["reason"]
    assert log.last_end["restored"] is True
    assert torch.equal(probe.read_many(ioc.setpoint_pvs[:2]), start)
    if offset < 0.05:
        assert final_setpoints(ioc, mark) == start.tolist()
        assert worst_step(ioc, mark) <= 1 + 1e-9
    else:  # the first set was to the setpoints found: nothing changed, nothing was put
        assert [p for p in ioc.puts(mark) if p.get("knob") in KNOBS] == []


def test_a_stuck_readback_never_breaks_the_step_limit(ioc, probe, ring, tmp_path, capsys,
                                                      with_optimize, monkeypatch,
                                                      run_mode):  # fmt: skip
    """The second knob's readback stops following (a stuck supply) mid-run: the next set fails
    its readback check; the restore ramps the SETPOINTS back from the last acknowledged ones
    within max_step (never from the stuck readback), the readback check then fails, and the run
    exits 3 printing the last acknowledged setpoint — which is what the IOC holds (a track run
    too: after a failure it restores the initial knobs, not its estimate)."""
    start = start_of(ring)
    probe.write_many(ioc.setpoint_pvs[:2], start)
    mark = ioc.n_puts()
    machine = {"kind": "epics", "settle_time": 0.1, "timeout": 0.4, "stale_timeout": 1.0}
    config = write_config(tmp_path, ioc, ring, machine=machine, **run_mode)
    real, stuck = EpicsMachine.read, []

    def read(self):  # the first read after the second knob left its start: it sticks there
        if not stuck and probe.read(ioc.setpoint_pvs[1]) != float(start[1]):
            stuck.append(probe.write(ioc.stuck_knob_pv, 2))
        return real(self)

    monkeypatch.setattr(EpicsMachine, "read", read)
    with pytest.warns(UserWarning, match="could not restore the initial knobs"):
        code, captured = run(config, capsys)
    assert code == 3, captured.err
    log = read_log(tmp_path / "run.jsonl")
    end = log.last_end
    assert end["restored"] is False and "ReadbackError" in end["reason"]
    held = final_setpoints(ioc, mark)
    assert held == start.tolist() == end["last_setpoint"] == end["final_setpoints"]
    last = ", ".join(f"{n}={v:.6g}" for n, v in zip(KNOBS, held, strict=True))
    assert f"last setpoint acknowledged: {last}" in captured.out
    assert "the knobs against the restore target:" in captured.out
    stuck = probe.read(ioc.readback_pvs[1])
    assert end["final_knobs"][1] == stuck != start[1]
    assert worst_step(ioc, mark) <= 1 + 1e-9


def test_a_glitch_averaged_into_the_range_is_still_discarded(ioc, probe, ring, tmp_path, capsys,
                                                             with_optimize):  # fmt: skip
    """With two readings averaged per evaluation, one reading of 150 mA/min (outside the PV's
    range) averaged with a normal one lands inside the range (about 75): the single reading is
    checked too, so the evaluation's reading is discarded and taken again, never the best."""
    probe.write_many(ioc.setpoint_pvs[:2], start_of(ring))
    probe.write(ioc.glitch_value_pv, 150.0)
    machine = {"kind": "epics", "settle_time": 0.1, "timeout": 1.0, "stale_timeout": 1.0,
               "n_average": 2, "average_interval": 0.06}  # fmt: skip
    config = write_config(tmp_path, ioc, ring, machine=machine, budget=5)
    with fault_at_read(5 + 4, lambda: probe.write(ioc.glitch_readings_pv, 1)):  # 5: the noise
        code, captured = run(config, capsys)
    assert code == 0, captured.err
    log = read_log(tmp_path / "run.jsonl")
    assert len(log.discarded) == 1 and 50.0 < log.discarded[0]["y"] < 100.0
    assert (
        "reading 150 outside the objective range [0, 100] (reading 1 of 2 averaged)"
        in (log.discarded[0]["reason"])
    )
    assert float(log.Y().max()) < 5.0
    assert log.evaluations[log.discarded[0]["step"]]["reads"] >= 2  # read again
    assert torch.equal(probe.read_many(ioc.setpoint_pvs[:2]), start_of(ring))
