"""Safety rules of the loop on any machine: checked settings, ramps, read retries, the objective
floor, restores verified by readback, signals, and what the run log holds after a failure."""

from __future__ import annotations

import itertools
import math
import os
import signal

import pytest
import torch
from botorch.models import SingleTaskGP
from botorch.models.transforms import Normalize
from gpytorch.kernels import RBFKernel, ScaleKernel
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pigp_torch.data.runlog import read_log, replay
from pigp_torch.loop import RunAborted, Terminated, optimize
from pigp_torch.machine import GuardedMachine, MachineError, ReadError
from pigp_torch.optimizers import RCDS, BayesOpt, NelderMead
from pigp_torch.optimizers.base import AskTellOptimizer
from tests.loop.problems import BOUNDS, D, bowl

#: The optimizer classes this property test drives, by their ``name``.
CLASSES = {cls.name: cls for cls in (BayesOpt, NelderMead, RCDS)}


class Walk(AskTellOptimizer):
    """Each ask moves the last point by +step on every knob (clamped to the bounds)."""

    name = "walk"

    def __init__(self, bounds, step=0.1, **kwargs):
        super().__init__(bounds, **kwargs)
        self.step = step

    def ask(self):
        return torch.clamp(self.X[-1] + self.step, self.bounds[0], self.bounds[1])


class FaultyMachine(GuardedMachine):
    """Reads bowl(x); ``faults`` maps a read number (1-based) to a value or an exception to
    return/raise instead; ``fail_on_set`` raises MachineError on that set (1-based)."""

    def __init__(self, faults=None, fail_on_set=None, x_init=(0.1, 0.2), **kwargs):
        super().__init__(BOUNDS, ["qs1", "qs2"], x_init=list(x_init), **kwargs)
        self.faults = dict(faults or {})
        self.fail_on_set = fail_on_set
        self.n_reads = self.n_sets = 0
        self.sets: list[torch.Tensor] = []

    def _apply(self, x):
        self.n_sets += 1
        if self.n_sets == self.fail_on_set:
            raise MachineError("power supply tripped")
        self.sets.append(x.clone())

    def read(self):
        self.n_reads += 1
        fault = self.faults.get(self.n_reads)
        if isinstance(fault, BaseException):
            raise fault
        if fault is not None:
            return fault
        return bowl(self._x)


INITIAL = [0.1, 0.2]


def test_invalid_readings_are_retried_up_to_read_retries(tmp_path):
    """NaN, inf, ReadError and TimeoutError count as invalid; two of them within one evaluation
    are retried (read_retries=2) and the log says how many attempts it took."""
    faults = {3: float("nan"), 4: ReadError("timeout"), 7: float("inf"), 8: TimeoutError("ca")}
    m = FaultyMachine(faults)
    table = optimize(m, Walk(BOUNDS), None, 5, read_retries=2, log=tmp_path / "r.jsonl")
    assert table["y"].tolist() == pytest.approx(
        [bowl(table.loc[k, ["qs1", "qs2"]].tolist()) for k in range(5)]
    )
    log = read_log(tmp_path / "r.jsonl")
    assert [e["reads"] for e in log.evaluations] == [1, 1, 3, 1, 3]
    assert m.n_reads == 9 and log.last_end["status"] == "completed"


def test_more_invalid_readings_than_retries_abort_and_restore(tmp_path):
    """k = retries + 1 invalid readings in a row: ReadError, knobs back at the initial setting,
    the log ends 'aborted' after the completed evaluations."""
    faults = {3: float("nan"), 4: float("nan"), 5: float("nan")}
    m = FaultyMachine(faults)
    with pytest.raises(ReadError, match="no valid reading in 3 attempts"):
        optimize(m, Walk(BOUNDS), None, 6, read_retries=2, log=tmp_path / "r.jsonl")
    assert m.get().tolist() == INITIAL
    log = read_log(tmp_path / "r.jsonl")
    assert log.n_evaluations == 2
    assert log.last_end["status"] == "aborted" and "ReadError" in log.last_end["reason"]
    assert log.last_end["final_knobs"] == INITIAL and log.last_end["restored_to"] == "initial"
    m = FaultyMachine({1: float("nan")})
    with pytest.raises(ReadError, match="in 1 attempts"):
        optimize(m, Walk(BOUNDS), None, 3, read_retries=0)


def test_machine_error_mid_run_restores_and_the_log_keeps_every_evaluation(tmp_path):
    """A MachineError on the 5th set: the initial knobs are restored and the log holds the 4
    completed evaluations exactly as measured."""
    m = FaultyMachine(fail_on_set=5)
    rows = []
    with pytest.raises(MachineError, match="power supply tripped"):
        optimize(m, Walk(BOUNDS), [-0.5, -0.5], 10, log=tmp_path / "r.jsonl", callback=rows.append)
    assert m.get().tolist() == INITIAL
    log = read_log(tmp_path / "r.jsonl")
    assert log.n_evaluations == 4 == len(rows)
    assert log.X().tolist() == [[r["qs1"], r["qs2"]] for r in rows]
    assert log.Y().tolist() == [r["y"] for r in rows]
    assert log.last_end["status"] == "aborted" and log.last_end["final_knobs"] == INITIAL


def test_objective_floor_aborts_after_recording_the_reading(tmp_path):
    """A reading below objective_floor is logged, then RunAborted; the knobs go back."""
    m = FaultyMachine({4: 0.05})
    with pytest.raises(RunAborted, match=r"below the floor 0\.1"):
        optimize(m, Walk(BOUNDS), None, 10, objective_floor=0.1, log=tmp_path / "r.jsonl")
    log = read_log(tmp_path / "r.jsonl")
    assert log.Y().tolist()[-1] == 0.05 and log.n_evaluations == 4
    assert log.last_end["status"] == "aborted" and m.get().tolist() == INITIAL


def test_restore_best_is_verified_by_readback(tmp_path):
    """restore='best' ends at the best point when the readback agrees and fresh readings there
    reproduce the best reading; a knob that does not follow fails the readback check at the
    best point, and the run then restores the initial knobs instead (and says so)."""
    m = FaultyMachine(x_init=(-0.2, -0.9))
    table = optimize(m, Walk(BOUNDS), None, 8, restore="best", log=tmp_path / "b.jsonl")
    assert m.get().tolist() == pytest.approx(
        table.loc[table["y"].idxmax(), ["qs1", "qs2"]].tolist()
    )
    end = read_log(tmp_path / "b.jsonl").last_end
    assert end["restored_to"] == "best (confirmed)"
    assert end["best_confirmation"]["readings"] == [table["y"].max()] * 3

    class Stuck(FaultyMachine):
        def get(self):  # the first knob's readback stays at the start
            x = super().get()
            x[0] = -0.2
            return x

    m = Stuck(x_init=(-0.2, -0.9))
    with pytest.warns(UserWarning, match=r"could not be set to the best point: readback check"):
        optimize(
            m,
            Walk(BOUNDS, step=0.01),
            None,
            3,
            restore="best",
            log=tmp_path / "s.jsonl",
            check_readings=False,  # the stuck readback would stop the run at its first reading
            restore_interval=0.0,
        )
    end = read_log(tmp_path / "s.jsonl").last_end
    assert end["status"] == "completed" and end["restored_to"] == "initial (best not confirmed)"
    assert end["restored"] is True and m.last_acknowledged.tolist() == [-0.2, -0.9]
    assert "readback check failed on knob indices [0]" in end["restore_errors"][0]


def test_the_loop_refuses_settings_a_bare_machine_would_accept():
    """A machine with no checks of its own: the loop still refuses a proposal outside the bounds
    (before calling set) and restores the start."""

    class Bare(GuardedMachine):  # the protocol's defaults, but a set that checks nothing
        def __init__(self):
            super().__init__(BOUNDS, ["a", "b"])
            self.sets = []

        def set(self, x):
            self.sets.append(x.clone())
            self._x = x.clone()

        def read(self):
            return bowl(self._x)

    class Escape(Walk):
        def ask(self):
            return self.X[-1] + 0.6  # no clamp: leaves the box on the second ask

    m = Bare()
    with pytest.raises(ValueError, match="outside bounds"):
        optimize(m, Escape(BOUNDS), [0.3, 0.3], 5)
    assert all(bool(((s >= -1) & (s <= 1)).all()) for s in m.sets)
    assert m.get().tolist() == [0.0, 0.0]


def test_ramp_moves_split_every_proposal_within_max_step():
    """Nelder–Mead, which has no step limit, reaches each proposal in steps of at most
    0.99 max_step and is read once per proposal; a move within that is exactly one set."""
    m = FaultyMachine(max_step=0.05, x_init=(0.0, 0.0))
    table = optimize(m, NelderMead(BOUNDS, initial_simplex_size=0.3), None, 12)
    assert m.n_reads == 12 and len(m.sets) > 12
    path = [torch.zeros(2, dtype=D), *m.sets]  # from x_init
    steps = torch.stack([(b - a).abs() for a, b in itertools.pairwise(path)])
    assert float(steps.max()) <= 0.05 * 0.99 + 1e-12
    assert table.loc[3, ["qs1", "qs2"]].tolist() != [0.0, 0.0]
    wide = FaultyMachine(max_step=1.0, x_init=(0.0, 0.0))  # 1.0 per knob per set
    table = optimize(wide, NelderMead(BOUNDS, initial_simplex_size=0.3), None, 12)
    moves = table[["qs1", "qs2"]].diff().abs().max(axis=1).iloc[1:].to_numpy()
    n_sets = [max(1, math.ceil(float(d) / 0.99)) for d in moves]
    assert 1 in n_sets and 2 in n_sets  # both kinds of move happen in this run
    last = float(table[["qs1", "qs2"]].iloc[-1].abs().max())
    restore = max(1, math.ceil(last / 0.99))  # back to the initial knobs (0, 0)
    # the start, then ceil(move / (0.99 m)) sets per evaluation, then the restore
    assert len(wide.sets) == 1 + sum(n_sets) + restore


def test_sigterm_takes_the_ctrl_c_path_and_the_handler_is_put_back(tmp_path):
    """SIGTERM during a read raises Terminated (a KeyboardInterrupt) after the restore; the
    previous SIGTERM handler is back afterwards; the log ends 'interrupted'."""
    previous = signal.getsignal(signal.SIGTERM)

    class Killed(FaultyMachine):
        def read(self):
            if self.n_reads == 2:
                os.kill(os.getpid(), signal.SIGTERM)
            return super().read()

    m = Killed()
    with pytest.raises(Terminated):
        optimize(m, Walk(BOUNDS), [-0.5, -0.5], 10, log=tmp_path / "r.jsonl")
    assert signal.getsignal(signal.SIGTERM) is previous
    assert m.get().tolist() == INITIAL
    end = read_log(tmp_path / "r.jsonl").last_end
    assert end["status"] == "interrupted" and "SIGTERM" in end["reason"]
    assert end["final_knobs"] == INITIAL and issubclass(Terminated, KeyboardInterrupt)


def test_a_signal_during_the_restore_is_deferred(tmp_path):
    """Ctrl-C while the knobs are being restored after a completed run does not cut the restore
    short: it completes, the log notes the signal, a warning says it was ignored."""

    class Impatient(FaultyMachine):
        def _apply(self, x):
            super()._apply(x)
            if self.n_reads == 4 and not getattr(self, "sent", False):
                self.sent = True
                os.kill(os.getpid(), signal.SIGINT)

    m = Impatient()
    with pytest.warns(UserWarning, match="SIGINT.*ignored"):
        table = optimize(m, Walk(BOUNDS), [-0.5, -0.5], 4, log=tmp_path / "r.jsonl")
    assert len(table) == 4 and m.get().tolist() == INITIAL
    end = read_log(tmp_path / "r.jsonl").last_end
    assert end["status"] == "completed" and end["deferred_signals"] == ["SIGINT"]


# ------------------------------------------------------------------------------------ properties
class Recorder(GuardedMachine):
    """A machine with no checks of its own (the protocol's defaults, a ``set`` that checks
    nothing) that records every setting it is sent."""

    def __init__(self, bounds, max_step, x_init, f, noise, seed):
        super().__init__(bounds, [f"k{i}" for i in range(bounds.shape[1])], x_init=x_init)
        self.max_step = max_step
        self.sets = [x_init.clone()]
        self.f, self.noise = f, noise
        self.gen = torch.Generator().manual_seed(seed)

    def set(self, x):
        self.sets.append(torch.as_tensor(x, dtype=D).clone())
        self._x = self.sets[-1].clone()

    def read(self):
        return self.f(self._x) + self.noise * float(torch.randn((), generator=self.gen, dtype=D))


def build(name, bounds, seed):
    """A fresh optimizer of the registry; BayesOpt with a cheap fixed-hyperparameter GP."""
    if name == "bo":

        def factory(X, Y):
            k = ScaleKernel(RBFKernel()).to(D)
            k.base_kernel.lengthscale = 0.3  # in the unit cube (Normalize below)
            k.outputscale = 1.0
            gp = SingleTaskGP(
                X,
                Y,
                torch.full_like(Y, 1e-3),
                covar_module=k,
                input_transform=Normalize(X.shape[-1], bounds=bounds),
                outcome_transform=None,
            )
            return gp.eval()

        return CLASSES[name](
            bounds,
            factory,
            step_limit=0.25,
            num_restarts=2,
            raw_samples=16,
            seed=seed,
            options={"maxiter": 20},
        )
    if name == "rcds":
        return CLASSES[name](bounds, noise=0.05)
    return CLASSES[name](bounds)


@st.composite
def problems(draw):
    d = draw(st.integers(1, 3))
    lo = torch.tensor(draw(st.lists(st.floats(-5, 5), min_size=d, max_size=d)), dtype=D)
    width = torch.tensor(draw(st.lists(st.floats(0.01, 10), min_size=d, max_size=d)), dtype=D)
    bounds = torch.stack([lo, lo + width])
    frac = draw(st.floats(0.02, 1.0))
    u0 = torch.tensor(draw(st.lists(st.floats(0, 1), min_size=d, max_size=d)), dtype=D)
    center = torch.tensor(draw(st.lists(st.floats(0, 1), min_size=d, max_size=d)), dtype=D)
    noise = draw(st.sampled_from([0.0, 0.01, 0.3]))
    return bounds, frac, bounds[0] + u0 * width, bounds[0] + center * width, noise


@pytest.mark.parametrize("name", sorted(CLASSES))
@settings(
    max_examples=6, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow]
)
@given(problem=problems(), seed=st.integers(0, 100))
def test_no_setting_leaves_the_bounds_or_the_step_limit(name, problem, seed):
    """For every optimizer, random boxes, step limits and noise: every point sent to the machine
    lies in the bounds and within max_step of the previous one; BayesOpt asks in its trust box."""
    bounds, frac, x_init, center, noise = problem
    width = bounds[1] - bounds[0]

    def f(x):
        return float(1.0 - (((x - center) / width) ** 2).sum())

    limit = frac * width / 2
    m = Recorder(bounds, limit, x_init, f, noise, seed)
    opt = build(name, bounds, seed)
    boxes = []

    def check_trust_box(row):
        if name == "bo" and row["step"] > 0:
            x = torch.tensor([row[k] for k in m.knob_names], dtype=D)
            lo, hi = opt.last_info["trust_lower"], opt.last_info["trust_upper"]
            boxes.append(bool(((x >= lo) & (x <= hi)).all()))

    table = optimize(m, opt, None, 7, callback=check_trust_box)
    assert len(table) == 7
    S = torch.stack(m.sets)
    assert bool(((S >= bounds[0]) & (S <= bounds[1])).all())
    assert bool(((S[1:] - S[:-1]).abs() <= limit * (1 + 1e-9)).all())
    assert torch.equal(m.get(), x_init)  # restored
    if name == "bo":
        assert boxes and all(boxes)


@pytest.mark.parametrize("name", ["nelder-mead", "rcds"])
@settings(max_examples=5, deadline=None, derandomize=True)
@given(crash_at=st.integers(1, 10), d=st.integers(1, 3))
def test_resume_after_any_crash_reproduces_the_run(tmp_path_factory, name, crash_at, d):
    """A crash after any step, then replay + continue: the same rows as a run without crash."""
    bounds = torch.stack([-torch.ones(d, dtype=D), torch.ones(d, dtype=D)])

    def f(x):  # rough but reproducible: a deterministic "noise" term of the point
        return float(-(x**2).sum() + 0.05 * torch.sin(1e3 * x).sum())

    x0 = torch.full((d,), 0.4, dtype=D)
    reference = optimize(f, build(name, bounds, 0), x0, 12)

    def crash(row):
        if row["step"] == crash_at:
            raise RuntimeError("crash")

    path = tmp_path_factory.mktemp("resume") / "r.jsonl"
    with pytest.raises(RuntimeError):
        optimize(f, build(name, bounds, 0), x0, 12, log=path, callback=crash)
    records = read_log(path)
    assert records.n_evaluations == crash_at + 1
    resumed = optimize(f, build(name, bounds, 0), None, 12, log=path, resume=records)
    cols = [*(f"x{i}" for i in range(d)), "y"]
    assert resumed[cols].values.tolist() == reference[cols].values.tolist()
    again = build(name, bounds, 0)
    assert replay(again, read_log(path)) == 12


# ------------------------------------------------------------------ crashes, restores, readings
def test_resume_restores_the_first_starts_knobs_not_where_a_crash_left_them(tmp_path):
    """A run killed hard (no end record) leaves the knobs at its last setting; the resumed run
    restores the knobs logged by the first start, notes where it found them, and ramps there
    within the step limit."""
    path = tmp_path / "r.jsonl"
    m = FaultyMachine(max_step=0.1)
    optimize(m, Walk(BOUNDS), None, 4, log=path)
    lines = path.read_text().splitlines(keepends=True)
    path.write_text("".join(lines[:-1]))  # as if SIGKILLed before the end record
    crashed = read_log(path)
    crash_point = crashed.X()[-1]
    assert crashed.last_end is None and crashed.initial_knobs == INITIAL
    m2 = FaultyMachine(max_step=0.1, x_init=crash_point.tolist())  # the knobs where it stopped
    optimize(m2, Walk(BOUNDS), None, 6, log=path, resume=crashed)
    assert m2.get().tolist() == pytest.approx(INITIAL, abs=1e-12)
    log = read_log(path)
    assert log.starts[-1]["initial_knobs"] == INITIAL
    assert log.starts[-1]["found_knobs"] == crash_point.tolist()
    assert log.last_end["restored"] is True and log.last_end["final_knobs"] == pytest.approx(
        INITIAL
    )
    path_sets = [crash_point, *m2.sets]
    steps = torch.stack([(b - a).abs() for a, b in itertools.pairwise(path_sets)])
    assert float(steps.max()) <= 0.1 + 1e-12


def test_an_intent_record_precedes_every_set(tmp_path):
    """Every setting the loop writes (ramp parts, the restore) is in the log as an intent before
    the write: the intents are exactly the machine's sets, in order."""
    m = FaultyMachine(max_step=0.1)
    seen = []

    class Watching(FaultyMachine):
        def _apply(self, x):
            seen.append(read_log(tmp_path / "r.jsonl").last_intent["x"])  # already on disk
            super()._apply(x)

    m = Watching(max_step=0.1)
    optimize(m, Walk(BOUNDS), None, 4, log=tmp_path / "r.jsonl")
    log = read_log(tmp_path / "r.jsonl")
    assert [i["x"] for i in log.intents] == [s.tolist() for s in m.sets] == seen
    assert {i["purpose"] for i in log.intents} == {"evaluation", "restore initial"}
    assert log.intents[-1]["x"] == INITIAL and log.last_end["last_setpoint"] == INITIAL
    for e in log.evaluations:  # the last intent before an evaluation is its setting
        before = [i for i in log.intents if i["_line"] < e["_line"]]
        assert before[-1]["x"] == e["x"] and before[-1]["step"] == e["step"]


def test_a_failed_restore_is_retried_and_the_end_record_says_so(tmp_path):
    """The restore's ramp of every knob fails (a power supply trips once): the knobs then go one
    by one in the same attempt and the end record names the trip; when every attempt fails the
    end record has restored false and the last setpoint written."""

    class TripsOnce(FaultyMachine):
        def _apply(self, x):
            back = torch.equal(x, torch.tensor(INITIAL, dtype=D)) and self.n_reads >= 3
            if back and not getattr(self, "tripped", 0):
                self.tripped = 1
                raise MachineError("power supply tripped during the restore")
            super()._apply(x)

    m = TripsOnce()
    optimize(m, Walk(BOUNDS), None, 3, log=tmp_path / "a.jsonl", restore_interval=0.0)
    end = read_log(tmp_path / "a.jsonl").last_end
    assert end["restored"] is True and end["restore_attempts"] == 1
    assert "power supply tripped" in end["restore_errors"][0] and m.get().tolist() == INITIAL
    assert end["restore_errors"][0].endswith("(then ramped knob by knob)")

    class NeverBack(FaultyMachine):
        def _apply(self, x):
            if torch.equal(x, torch.tensor(INITIAL, dtype=D)) and self.n_reads >= 3:
                raise MachineError("interlock")
            super()._apply(x)

    m = NeverBack()
    with pytest.raises(MachineError, match="interlock"):
        optimize(m, Walk(BOUNDS), None, 3, log=tmp_path / "b.jsonl", restore_interval=0.0)
    end = read_log(tmp_path / "b.jsonl").last_end
    assert end["restored"] is False and end["restore_attempts"] == 3
    # the interlock refused every restoring set: the last setpoint acknowledged is where the
    # knobs are, not the restore target that was intended (and logged as an intent)
    assert end["restored_to"] == "initial (failed)" and end["last_intended"] == INITIAL
    assert end["last_setpoint"] == end["final_knobs"] == m.get().tolist() != INITIAL


def test_a_reading_taken_while_the_machine_changed_is_discarded(tmp_path):
    """A disconnection during a reading: the reading is discarded (logged) and taken again.
    Readbacks that left the setting during a reading (an IOC reboot): discarded, and the run
    aborts with MachineError; no evaluation holds the bad reading."""

    class Blip(FaultyMachine):
        disconnections = 0

        def read(self):
            y = super().read()
            if self.n_reads == 3:
                self.disconnections += 1
                return -100.0  # what a reading across a reconnect may look like
            return y

    m = Blip()
    optimize(m, Walk(BOUNDS), None, 4, log=tmp_path / "a.jsonl")
    log = read_log(tmp_path / "a.jsonl")
    assert [d["step"] for d in log.discarded] == [2] and log.discarded[0]["y"] == -100.0
    assert "disconnection" in log.discarded[0]["reason"]
    assert -100.0 not in log.Y().tolist() and log.evaluations[2]["reads"] == 2

    class Reboot(FaultyMachine):
        def read(self):
            y = super().read()
            if self.n_reads == 3:
                self._x = torch.zeros(2, dtype=D)  # the IOC came back with every knob at 0
            return y

    m = Reboot()
    with pytest.raises(MachineError, match="reading discarded and the knobs moved"):
        optimize(m, Walk(BOUNDS), None, 6, log=tmp_path / "b.jsonl")
    log = read_log(tmp_path / "b.jsonl")
    assert log.n_evaluations == 2 and [d["step"] for d in log.discarded] == [2]
    assert log.last_end["status"] == "aborted" and m.get().tolist() == INITIAL


def test_sighup_takes_the_sigterm_path(tmp_path):
    """SIGHUP (terminal closed) during a run: Terminated with signum SIGHUP, knobs restored, the
    log ends 'interrupted' naming SIGHUP; the previous handler is put back. (SIGHUP starts at
    its default here, also when the test runner itself was started under nohup.)"""
    outer = signal.signal(signal.SIGHUP, signal.SIG_DFL)
    try:
        _sighup_run(tmp_path)
    finally:
        signal.signal(signal.SIGHUP, outer)


def _sighup_run(tmp_path):
    previous = signal.getsignal(signal.SIGHUP)

    class HungUp(FaultyMachine):
        def read(self):
            if self.n_reads == 2:
                os.kill(os.getpid(), signal.SIGHUP)
            return super().read()

    m = HungUp()
    with pytest.raises(Terminated) as info:
        optimize(m, Walk(BOUNDS), [-0.5, -0.5], 10, log=tmp_path / "r.jsonl")
    assert info.value.signum == signal.SIGHUP
    assert signal.getsignal(signal.SIGHUP) is previous and m.get().tolist() == INITIAL
    end = read_log(tmp_path / "r.jsonl").last_end
    assert end["status"] == "interrupted" and "SIGHUP" in end["reason"]


def test_an_ignored_sighup_stays_ignored(tmp_path):
    """Started under nohup (SIGHUP ignored), a run is not stopped by SIGHUP."""
    previous = signal.signal(signal.SIGHUP, signal.SIG_IGN)
    try:

        class HungUp(FaultyMachine):
            def read(self):
                if self.n_reads == 2:
                    os.kill(os.getpid(), signal.SIGHUP)
                return super().read()

        table = optimize(HungUp(), Walk(BOUNDS), [-0.5, -0.5], 4, log=tmp_path / "r.jsonl")
        assert len(table) == 4 and signal.getsignal(signal.SIGHUP) == signal.SIG_IGN
        assert read_log(tmp_path / "r.jsonl").last_end["status"] == "completed"
    finally:
        signal.signal(signal.SIGHUP, previous)


def test_two_signals_during_the_restore_say_what_is_known(tmp_path):
    """SIGTERM stops the run; two more arrive during the restore, just after its last set: the
    restore is abandoned, so the run reports NOT restored (pessimistic) — but the end record
    and the summary say what is known: the last acknowledged setpoint, and the setpoints and
    readbacks against the restore target (here exactly back)."""
    from io import StringIO

    from pigp_torch.commands.optimize_output import print_summary

    class Signals(FaultyMachine):
        def read(self):
            if self.n_reads == 2:
                os.kill(os.getpid(), signal.SIGTERM)
            return super().read()

        def set(self, x):
            super().set(x)
            if self.n_reads >= 2 and torch.equal(self._x, torch.tensor(INITIAL, dtype=D)):
                os.kill(os.getpid(), signal.SIGTERM)
                os.kill(os.getpid(), signal.SIGTERM)

    m = Signals()
    path = tmp_path / "r.jsonl"
    with pytest.warns(UserWarning, match="could not restore"), pytest.raises(Terminated):
        optimize(m, Walk(BOUNDS), [-0.5, -0.5], 10, log=path, max_step=0.2)
    end = read_log(path).last_end
    assert end["restored"] is False and end["deferred_signals"] == ["SIGTERM", "SIGTERM"]
    assert end["last_setpoint"] == end["final_setpoints"] == end["restore_target"] == INITIAL
    assert end["final_knobs"] == INITIAL and m.get().tolist() == INITIAL
    out = StringIO()
    print_summary(path, out)
    text = out.getvalue()
    assert "KNOBS NOT RESTORED" in text and "last setpoint acknowledged: qs1=0.1, qs2=0.2" in text
    rows = [ln.split() for ln in text.splitlines() if ln.strip().startswith("qs")]
    assert [r[0] for r in rows] == ["qs1", "qs2"]
    assert all(float(r[3]) == 0.0 and float(r[5]) == 0.0 for r in rows)  # sp/rb - target
