"""Track mode (:func:`pigp_torch.loop.track`): stops at the time limit, the count limit or a
signal; where the knobs are left; the tracked unknowns in each record; failures and resume."""

from __future__ import annotations

import os
import signal

import pytest
import torch

from pigp_torch.data.runlog import read_log
from pigp_torch.loop import RunOptions, Terminated, optimize, track
from pigp_torch.machine import GuardedMachine, MachineError
from pigp_torch.optimizers import NelderMead
from pigp_torch.optimizers.base import AskTellOptimizer
from tests.loop.problems import BOUNDS, D, bowl

INITIAL = [0.1, 0.2]
ESTIMATE = [0.25, -0.15]


class Drifting(GuardedMachine):
    """A bowl whose top moves +0.01 per reading on the first knob (a drifting machine);
    ``values`` (read number, 1-based -> value) replaces a reading; ``fail_on_read`` raises a
    MachineError; ``on_read`` (read number -> None) runs before each read."""

    def __init__(self, values=None, fail_on_read=None, on_read=None):
        super().__init__(BOUNDS, ["qs1", "qs2"], x_init=list(INITIAL))
        self.values, self.fail_on_read, self.on_read = dict(values or {}), fail_on_read, on_read
        self.n_reads = 0
        self.sets: list[list[float]] = []

    def _apply(self, x):
        self.sets.append(x.tolist())

    def read(self):
        self.n_reads += 1
        if self.on_read is not None:
            self.on_read(self.n_reads)
        if self.n_reads == self.fail_on_read:
            raise MachineError("power supply tripped")
        if self.n_reads in self.values:
            return self.values[self.n_reads]
        shift = torch.tensor([0.01 * self.n_reads, 0.0], dtype=D)
        return bowl(self._x - shift)


class FakeTracker(AskTellOptimizer):
    """Walks +0.05 per ask on every knob; recommends ``estimate``; tracks the number of
    readings told (``"told"``, in readings) and a made-up offset (``n_told * 1e-5`` m)."""

    name = "fake-tracker"

    def __init__(self, bounds, estimate=ESTIMATE, **kwargs):
        super().__init__(bounds, **kwargs)
        self.estimate = estimate

    def ask(self):
        return torch.clamp(self.X[-1] + 0.05, self.bounds[0], self.bounds[1])

    def recommend(self):
        return torch.as_tensor(self.estimate, dtype=D)

    def tracked(self):
        return {"told": (float(self.n_told), "readings"), "offset": (self.n_told * 1e-5, "m")}


def reads_clock(machine):
    """A clock that advances 1 s per reading of ``machine`` (time compressed, deterministic)."""
    return lambda: float(machine.n_reads)


def test_the_time_limit_ends_the_run_at_the_estimate_with_tracked_in_each_record(tmp_path):
    """1 s per reading and a 5 s limit: five readings, then the knobs at the recommendation
    (the end record says so); each record carries the tracker's estimate when it was asked and
    its wall-clock times."""
    m = Drifting()
    table = track(m, FakeTracker(BOUNDS), 1000, time_limit_s=5.0, clock=reads_clock(m),
                  log=tmp_path / "t.jsonl")  # fmt: skip
    assert len(table) == 5 and m.n_reads == 5
    assert m.get().tolist() == ESTIMATE and m.sets[-1] == ESTIMATE
    log = read_log(tmp_path / "t.jsonl")
    end = log.last_end
    assert (
        end["status"] == "completed"
        and "time limit of 5 s passed after 5 readings" in (end["reason"])
    )
    assert end["restored_to"] == "estimate" and end["restore_target"] == ESTIMATE
    assert end["restored"] is True and end["knobs_not_at_target"] == []
    told = [e["tracked"]["told"] for e in log.evaluations]
    assert told == [[float(k), "readings"] for k in range(5)]  # the estimate it was asked with
    assert log.evaluations[3]["tracked"]["offset"] == [pytest.approx(3e-5), "m"]
    times = [e["t_read"] for e in log.evaluations]
    assert times == sorted(times) and all(e["t_set"] <= e["t_read"] for e in log.evaluations)


def test_max_readings_bounds_the_count():
    m = Drifting()
    table = track(m, FakeTracker(BOUNDS), 7, time_limit_s=3600.0)
    assert len(table) == 7 and m.n_reads == 7 and m.get().tolist() == ESTIMATE


@pytest.mark.parametrize(("signum", "raised"), [(signal.SIGINT, KeyboardInterrupt),
                                                (signal.SIGTERM, Terminated)])  # fmt: skip
def test_a_stop_signal_leaves_the_knobs_at_the_estimate_then_re_raises(tmp_path, signum, raised):
    """The usual end of a shift: a signal at the 4th reading stops the run after it; the knobs
    go to the estimate (not the initial knobs), the signal is re-raised (the command's exit
    code follows it) and the handlers are put back. SIGINT starts at Python's default handler
    (a process started in the background by a shell without job control inherits it ignored,
    and an ignored SIGINT stays ignored by design)."""
    previous = signal.getsignal(signal.SIGTERM)
    m = Drifting(on_read=lambda n: os.kill(os.getpid(), signum) if n == 4 else None)
    previous_int = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(raised):
            track(m, FakeTracker(BOUNDS), 1000, time_limit_s=3600.0, log=tmp_path / "t.jsonl")
    finally:
        signal.signal(signal.SIGINT, previous_int)
    assert m.get().tolist() == ESTIMATE
    assert signal.getsignal(signal.SIGTERM) is previous
    end = read_log(tmp_path / "t.jsonl").last_end
    assert end["status"] == "interrupted" and end["restored_to"] == "estimate"


def test_a_machine_error_restores_the_initial_knobs(tmp_path):
    m = Drifting(fail_on_read=3)
    with pytest.raises(MachineError, match="tripped"):
        track(m, FakeTracker(BOUNDS), 1000, time_limit_s=3600.0, log=tmp_path / "t.jsonl")
    assert m.get().tolist() == INITIAL
    end = read_log(tmp_path / "t.jsonl").last_end
    assert end["status"] == "aborted" and end["restored_to"] == "initial"


def test_best_means_the_best_of_the_recent_readings():
    """Reading 2 is the best of the run (9.0) but old; among the last 3 readings the best is
    reading 6 (5.0): the knobs go to reading 6's setting."""
    m = Drifting(values={1: 0.0, 2: 9.0, 3: 1.0, 4: 2.0, 5: 3.0, 6: 5.0, 7: 4.0, 8: 1.0})
    table = track(m, FakeTracker(BOUNDS), 8, time_limit_s=3600.0, end_at="best", recent=3)
    assert table["y"].tolist() == [0.0, 9.0, 1.0, 2.0, 3.0, 5.0, 4.0, 1.0]
    assert m.get().tolist() == table.loc[5, ["qs1", "qs2"]].tolist()


def test_current_leaves_the_knobs_and_initial_puts_them_back():
    m = Drifting()
    table = track(m, FakeTracker(BOUNDS), 4, time_limit_s=3600.0, end_at="current")
    assert m.get().tolist() == table.loc[3, ["qs1", "qs2"]].tolist() != INITIAL
    m = Drifting()
    track(m, FakeTracker(BOUNDS), 4, time_limit_s=3600.0, end_at="initial")
    assert m.get().tolist() == INITIAL


def test_an_estimate_outside_the_bounds_is_not_used(tmp_path):
    m = Drifting()
    with pytest.warns(UserWarning, match="outside the knob bounds; restoring the initial knobs"):
        track(m, FakeTracker(BOUNDS, estimate=[2.0, 0.0]), 4, time_limit_s=3600.0,
              log=tmp_path / "t.jsonl")  # fmt: skip
    assert m.get().tolist() == INITIAL
    log = read_log(tmp_path / "t.jsonl")
    assert any("outside the knob bounds" in n["message"] for n in log.notices)
    assert log.last_end["restored_to"] == "initial"


def test_the_default_estimate_of_a_model_free_optimizer_is_its_best_reading():
    m = Drifting()
    opt = NelderMead(BOUNDS)
    table = track(m, opt, 12, time_limit_s=3600.0)
    best = table.loc[table["y"].idxmax(), ["qs1", "qs2"]].tolist()
    assert m.get().tolist() == pytest.approx(best, abs=1e-12)


def test_a_track_run_resumes_from_its_log(tmp_path):
    """Stopped after 4 readings (max_readings), continued to 9: the optimizer is rebuilt from
    the log, the count includes the logged readings, every record has its tracked estimate."""
    path = tmp_path / "t.jsonl"
    track(Drifting(), FakeTracker(BOUNDS), 4, time_limit_s=3600.0, log=path)
    m = Drifting()
    table = track(m, FakeTracker(BOUNDS), 9, time_limit_s=3600.0, log=path,
                  resume=read_log(path))  # fmt: skip
    assert len(table) == 9 and m.n_reads == 5
    log = read_log(path)
    assert log.n_evaluations == 9 and [e["tracked"]["told"][0] for e in log.evaluations] == [
        float(k) for k in range(9)
    ]
    assert m.get().tolist() == ESTIMATE


def test_bad_arguments_are_refused():
    m = Drifting()
    with pytest.raises(ValueError, match="time_limit_s must be positive"):
        track(m, FakeTracker(BOUNDS), 5, time_limit_s=0.0)
    with pytest.raises(ValueError, match="end_at must be one of"):
        track(m, FakeTracker(BOUNDS), 5, time_limit_s=1.0, end_at="somewhere")
    with pytest.raises(ValueError, match="max_readings must be a positive integer"):
        track(m, FakeTracker(BOUNDS), 0, time_limit_s=1.0)
    with pytest.raises(ValueError, match="initial or none, not best"):
        track(m, FakeTracker(BOUNDS), 5, time_limit_s=1.0, options=RunOptions(restore="best"))
    assert m.n_reads == 0


def test_a_one_shot_run_logs_no_tracked_field(tmp_path):
    optimize(Drifting(), FakeTracker(BOUNDS), budget=3, log=tmp_path / "o.jsonl")
    assert all("tracked" not in e for e in read_log(tmp_path / "o.jsonl").evaluations)


def test_a_track_run_keeps_only_its_last_evaluations_in_memory(tmp_path):
    """keep=5 of 12 readings: the table holds steps 7..11, the end record still counts 12 and
    the log holds all 12; end_at="best" picks among the kept ones."""
    m = Drifting()
    table = track(m, FakeTracker(BOUNDS), 12, time_limit_s=3600.0, keep=5, recent=5,
                  end_at="best", log=tmp_path / "t.jsonl")  # fmt: skip
    assert table["step"].tolist() == [7, 8, 9, 10, 11]
    log = read_log(tmp_path / "t.jsonl")
    assert log.n_evaluations == 12 and log.last_end["n_evaluations"] == 12
    best = table.loc[table["y"].idxmax(), ["qs1", "qs2"]].tolist()
    assert m.get().tolist() == best
    with pytest.raises(ValueError, match="keep must be an integer >= recent"):
        track(m, FakeTracker(BOUNDS), 5, time_limit_s=1.0, keep=3, recent=4)


def test_the_plausible_reading_rule_follows_the_recent_level():
    """With the noise stated, the median/MAD rule of a track run looks at its last ``keep``
    readings: a machine whose level stepped up by 100 sigma long ago is not re-read forever."""
    m = Drifting(values={k: (0.0 if k <= 6 else 4.0) + 0.01 * (k % 3) for k in range(1, 41)})
    table = track(m, FakeTracker(BOUNDS), 30, time_limit_s=3600.0, keep=5, recent=5,
                  options=RunOptions(noise=0.04))  # fmt: skip
    assert table["step"].tolist() == [25, 26, 27, 28, 29]
    # re-reads only while the new level is not yet the median of the last 5 readings
    assert 30 < m.n_reads <= 30 + 1 + 3


def test_an_estimate_the_machine_refuses_ends_at_the_initial_knobs(tmp_path):
    """The machine refuses the estimate's setting on every attempt: a warning, then the initial
    knobs (the end record says the estimate was not reached)."""

    class Refusing(Drifting):
        def _apply(self, x):
            if x.tolist() == ESTIMATE:
                raise MachineError("setting refused")
            super()._apply(x)

    m = Refusing()
    with pytest.warns(UserWarning, match="could not be set to the estimate.*initial knobs"):
        track(m, FakeTracker(BOUNDS), 4, time_limit_s=3600.0, log=tmp_path / "t.jsonl",
              options=RunOptions(restore_interval=0.0))  # fmt: skip
    assert m.get().tolist() == INITIAL
    end = read_log(tmp_path / "t.jsonl").last_end
    assert end["restored_to"] == "initial (estimate not reached)" and end["restored"] is True
    assert end["restore_target"] == INITIAL and end["restore_attempts"] == 3 + 1
