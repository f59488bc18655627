"""Which readings count, over real Channel Access (the shared simulated IOC on 127.0.0.1): a
glitch of twice the run's level when the run file states no noise (the noise is then measured
at the start), and readings served with an alarm severity. Where the knobs went is read from
the IOC's own put log (every put it accepted); what was read, from the run log.

Runs go through `pigp optimize` in this process; a fault is armed just before the n-th objective
read of the run (a patched ``EpicsMachine.read`` writes the IOC's switch first).
"""

from __future__ import annotations

import contextlib

import pytest
import torch

from pigp_torch import cli
from pigp_torch.data.runlog import read_log
from pigp_torch.machine.epics import EpicsMachine
from pigp_torch.machine.errors import SeverityError
from pigp_torch.simulated_epics import (
    ALARM_KNOB_SUFFIX,
    ALARM_READINGS_SUFFIX,
    ALARM_SEVERITY_SUFFIX,
)

from .conftest import FAST, NOISE
from .test_faults_over_ca import fault_at_read, private_locks, with_optimize  # noqa: F401
from .test_faults_over_ca import write_config as faults_config

pytestmark = pytest.mark.usefixtures("with_optimize")  # `pigp optimize` registered

KNOBS = ["01G-QSS4", "02G-QSS3", "05G-QSS3"]
START = [2.5, -1.25, 1.0]  # A: a nonzero start, so that a restore is visible
MAX_STEP = 0.1  # of the half-range (30 A): 3 A
NOISE_READS = 5  # the run file's default: readings of the noise measurement at the start


def alarm_pv(ioc, suffix: str) -> str:
    return f"{ioc.prefix}{suffix}"


@pytest.fixture
def alarms(ioc, probe):
    """The IOC's severity switches off (before and after): INVALID is what they would serve."""

    def reset():
        probe.write(alarm_pv(ioc, ALARM_READINGS_SUFFIX), 0)
        probe.write(alarm_pv(ioc, ALARM_KNOB_SUFFIX), 0)
        probe.write(alarm_pv(ioc, ALARM_SEVERITY_SUFFIX), 3)

    reset()
    yield ioc
    if ioc.alive():
        reset()


def write_config(tmp_path, ioc, ring, **over) -> str:
    """The run file of the fault tests, on the 3 knobs here (±30 A, max_step 0.1: 3 A)."""
    knobs = {k: [-30.0, 30.0] for k in KNOBS}
    return faults_config(tmp_path, ioc, ring, knobs=knobs, max_step=MAX_STEP, **over)


def final_setpoints(ioc, since: int) -> list[float]:
    """Each knob's setpoint after the last put the IOC accepted for it (from its put log)."""
    last = dict(zip(KNOBS, START, strict=True))
    for p in ioc.puts(since):
        if p.get("knob") in KNOBS:
            last[p["knob"]] = p["value"]
    return [last[k] for k in KNOBS]


def worst_step(ioc, since: int) -> float:
    """The largest step of a put the IOC accepted, in units of the step limit (3 A)."""
    puts = [p for p in ioc.puts(since) if p.get("knob") in KNOBS]
    return max((abs(p["value"] - p["previous"]) for p in puts), default=0.0) / (MAX_STEP * 30)


def level(probe, ioc, n: int = 8) -> float:
    """The loss rate at the start point: the mean of ``n`` reads 60 ms apart (mA/min)."""
    import time

    ys = []
    for _ in range(n):
        ys.append(probe.read(ioc.loss_rate_pv))
        time.sleep(0.06)
    return sum(ys) / n


def run(config, capsys):
    code = cli.main(["optimize", "--config", config, "--quiet"])
    return code, capsys.readouterr()


def evaluated_values(log) -> list[float]:
    """Every single reading averaged into an evaluation, and every evaluation's value."""
    out = [e["y"] for e in log.evaluations]
    for e in log.evaluations:
        out += list((e.get("reading") or {}).get("values") or [])
    return out


@pytest.mark.parametrize("repeats", [1, 2])
def test_a_2x_glitch_without_stated_noise_is_never_where_the_knobs_end(
    alarms, probe, ring, tmp_path, capsys, repeats
):
    """No objective_noise in the run file: the noise is measured at the start (5 readings at
    the initial setting, logged in the start record). A reading of twice the start's level
    after 4 evaluations (3 knobs, Nelder-Mead, max_step 0.1, restore: best): once, it is read
    again and discarded, never an evaluation; twice in a row (its re-read agrees), it becomes an
    evaluation and the best, and the best's fresh readings at the end do not reproduce it. In
    neither case do the knobs end there: the IOC's last setpoints are the restore target, and a
    best kept reads no worse than the start's control reading."""
    ioc = alarms
    probe.write_many(ioc.setpoint_pvs[:3], START)
    y0 = level(probe, ioc)
    glitch = round(2 * y0, 6)
    probe.write(ioc.glitch_value_pv, glitch)
    mark = ioc.n_puts()
    config = write_config(tmp_path, ioc, ring, restore="best")
    arm = NOISE_READS + 2 + 4  # the measurement, evaluation 1 (read twice), then 4 more reads
    with fault_at_read(arm, lambda: probe.write(ioc.glitch_readings_pv, repeats)):
        with contextlib.ExitStack() as stack:
            if repeats == 2:
                stack.enter_context(pytest.warns(UserWarning, match="did not reproduce"))
            code, captured = run(config, capsys)
    assert code == 0, captured.err
    log = read_log(tmp_path / "run.jsonl")
    noise = log.starts[0]["noise"]
    assert noise["source"] == "measured" and noise["n"] == NOISE_READS
    assert 0.01 < noise["sigma"] < 0.1  # the IOC's noise is 0.04 mA/min
    assert "reading noise: " in captured.out and "measured at the start from 5" in captured.out
    end = log.last_end
    target = end["restore_target"]
    assert final_setpoints(ioc, mark) == target  # what the IOC holds
    assert torch.equal(probe.read_many(ioc.setpoint_pvs[:3]), torch.tensor(target))
    if repeats == 1:
        assert glitch in [d["y"] for d in log.discarded]
        assert glitch not in evaluated_values(log)
        best = end["best"] or end["rejected_best"]  # rejected: it read below the start
        assert best["y"] < 1.5 * y0 and (end["best"] is not None or target == START)
    else:
        assert end["rejected_best"]["y"] == pytest.approx(glitch)
        assert end["best"] is None and target == START
    if end["restored_to"] == "best (confirmed)":
        conf = end["best_confirmation"]
        assert target == end["best"]["x"]
        if end["best"]["step"] > 0:  # else the best is the start point: no control reading
            assert conf["mean"] >= conf["control_mean"]
    assert worst_step(ioc, mark) <= 1 + 1e-9


def test_an_invalid_reading_is_never_an_evaluation(alarms, probe, ring, tmp_path, capsys):
    """One read of the loss rate is served with severity INVALID and a value close to the
    run's own (it would pass every other check): it is logged as discarded, naming the PV and
    the severity, read again, and is never an evaluation; the run completes."""
    ioc = alarms
    probe.write_many(ioc.setpoint_pvs[:3], START)
    served = round(level(probe, ioc) + 0.0123, 6)
    probe.write(ioc.glitch_value_pv, served)

    def arm():
        probe.write(ioc.glitch_readings_pv, 1)
        probe.write(alarm_pv(ioc, ALARM_READINGS_SUFFIX), 1)

    # The IOC's noise is stated (as in the other fault tests): measured from 5 readings at the
    # start, the estimate is below a quarter of the true noise in 0.7 % of runs, and one such
    # made the next evaluation's honest re-reads disagree and end the run (seen once in CI) --
    # a property of the measurement, not of the severity rule this test is about.
    config = write_config(tmp_path, ioc, ring, budget=5, objective_noise=NOISE)
    with fault_at_read(2 + 1, arm):  # evaluation 1 (read twice), then evaluation 2's first read
        code, captured = run(config, capsys)
    assert code == 0, captured.err
    log = read_log(tmp_path / "run.jsonl")
    assert [d["y"] for d in log.discarded] == [served]
    reason = log.discarded[0]["reason"]
    assert f"{ioc.loss_rate_pv} read with alarm severity INVALID" in reason
    assert served not in evaluated_values(log) and log.n_evaluations == 5
    assert log.last_end["restored"] is True
    assert torch.equal(probe.read_many(ioc.setpoint_pvs[:3]), torch.tensor(START))


@pytest.mark.parametrize("at", ["start", "mid-run"])
def test_an_always_invalid_objective_stops_the_run(alarms, probe, ring, tmp_path, capsys, at,
                                                   run_mode):  # fmt: skip
    """The loss rate is INVALID on every read (from before the run, or from the 9th read on):
    after the bounded re-reads (read_retries 2: 3 reads) the run stops with exit 1 and one line
    naming the PV and its severity; the knobs are where the run found them (from the start: the
    noise measurement reads before anything moves, and no put changed a setpoint); a track run
    likewise (after a failure it restores the initial knobs, not its estimate)."""
    ioc = alarms
    probe.write_many(ioc.setpoint_pvs[:3], START)
    mark = ioc.n_puts()
    config = write_config(tmp_path, ioc, ring, **run_mode)
    always = alarm_pv(ioc, ALARM_READINGS_SUFFIX)
    if at == "start":
        probe.write(always, -1)
    with fault_at_read(9, lambda: probe.write(always, -1)):
        code, captured = run(config, capsys)
    assert code == 1, captured.err + captured.out
    lines = [line for line in captured.err.splitlines() if "run aborted" in line]
    assert len(lines) == 1, captured.err
    assert lines == [
        f"pigp optimize: run aborted: SeverityError: {ioc.loss_rate_pv} read with alarm "
        f"severity INVALID on 3 reads in a row (value {lines[0].rsplit('value ', 1)[1]}"
    ]
    assert "Traceback" not in captured.err
    log = read_log(tmp_path / "run.jsonl")
    end = log.last_end
    assert end["status"] == "aborted" and end["restored"] is True
    assert end["restored_to"] == "initial"
    invalid = [d for d in log.discarded if "INVALID" in d["reason"]]
    assert len(invalid) == 3
    # a reading far from the run's median whose re-read (read 9 on) came back INVALID is also
    # discarded, unconfirmed; whether the read before the fault was such a step depends on the
    # ask and the IOC's noise, so it may or may not be there
    others = [d for d in log.discarded if "INVALID" not in d["reason"]]
    assert len(others) <= 1 and all("not confirmed" in d["reason"] for d in others)
    assert final_setpoints(ioc, mark) == START
    assert torch.equal(probe.read_many(ioc.setpoint_pvs[:3]), torch.tensor(START))
    if at == "start":
        assert log.n_evaluations == 0  # the restore's puts only: none moved a knob
        assert all(p["value"] == p["previous"] for p in ioc.puts(mark))
    else:
        assert log.n_evaluations >= 1
    assert worst_step(ioc, mark) <= 1 + 1e-9


def test_an_invalid_readback_is_not_a_readback(alarms, probe, ring):
    """A knob's readback served INVALID: get() raises SeverityError naming its PV; with
    refuse_severity MAJOR a MAJOR readback too, and a MINOR one is a readback."""
    ioc = alarms
    with EpicsMachine(ioc.knob_names, ring.bounds, ioc.loss_rate_pv, **FAST) as m:
        probe.write(alarm_pv(ioc, ALARM_KNOB_SUFFIX), 2)
        with pytest.raises(SeverityError, match=rf"{ioc.readback_pvs[1]} read with alarm "
                                                "severity INVALID"):  # fmt: skip
            m.get()
        probe.write(alarm_pv(ioc, ALARM_SEVERITY_SUFFIX), 2)
        probe.write(alarm_pv(ioc, ALARM_KNOB_SUFFIX), 2)  # served again, now MAJOR
        assert m.get().tolist() == [0.0] * len(ioc.knob_names)  # MAJOR: a readback by default
    probe.write(alarm_pv(ioc, ALARM_KNOB_SUFFIX), 0)
    with EpicsMachine(ioc.knob_names, ring.bounds, ioc.loss_rate_pv, refuse_severity="MAJOR",
                      **FAST) as m:  # fmt: skip
        probe.write(alarm_pv(ioc, ALARM_KNOB_SUFFIX), 2)  # MAJOR
        with pytest.raises(SeverityError, match="severity MAJOR"):
            m.get()
        probe.write(alarm_pv(ioc, ALARM_SEVERITY_SUFFIX), 1)
        probe.write(alarm_pv(ioc, ALARM_KNOB_SUFFIX), 2)  # MINOR
        assert m.get().tolist() == [0.0] * len(ioc.knob_names)
