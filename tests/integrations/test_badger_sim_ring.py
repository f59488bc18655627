"""The ``pigp_sim`` environment's routine bookkeeping on an in-memory machine (no Channel
Access): the start is recorded at Badger's start hooks, the end sets the start's or the best
reading's knobs, once, and SIGTERM in a routine raises Badger's own stop."""

from __future__ import annotations

import pytest
import torch

pytest.importorskip("badger")

from badger.errors import BadgerRunTerminated

from pigp_torch.badger_plugins.sim_ring import SimRingEnvironment
from pigp_torch.integrations.badger import SIM_KNOBS
from pigp_torch.machine.base import GuardedMachine

D = len(SIM_KNOBS)


class MemoryMachine(GuardedMachine):
    """Setpoints in memory; the reading is minus the distance to 5 A on every knob."""

    def __init__(self, x0):
        bounds = torch.tensor([[-30.0] * D, [30.0] * D], dtype=torch.float64)
        super().__init__(bounds, list(SIM_KNOBS), x_init=torch.as_tensor(x0, dtype=torch.float64))
        self.sets = 0

    def _apply(self, x):
        self.sets += 1

    def setpoints(self):
        return self.get()

    def read(self):
        return -float((self._x - 5.0).norm())


def _env(x0, **kw):
    env = SimRingEnvironment(**kw)
    env._epics = MemoryMachine(x0)
    return env


START = [0.5 * k - 3.0 for k in range(D)]


@pytest.mark.parametrize("hook", ["get_system_states", "reset_environment"])
def test_the_end_of_a_routine_sets_the_start_knobs_back(hook):
    """A start hook records the setpoints; after two settings the end sets them back, exactly,
    and a second end does nothing."""
    env = _env(START)
    getattr(env, hook)()
    for shift in (2.0, 4.0):
        env.set_variables({k: v + shift for k, v in zip(SIM_KNOBS, START, strict=True)})
        env.get_observables(["loss_rate"])
    assert env._epics.get().tolist() == [v + 4.0 for v in START]
    assert env.end_routine() == dict(zip(SIM_KNOBS, START, strict=True))
    assert env._epics.get().tolist() == START
    n = env._epics.sets
    assert env.end_routine() is None and env._epics.sets == n


def test_end_knobs_best_sets_the_highest_reading():
    """With end_knobs='best' the end sets the knobs of the highest reading (4 A above START is
    closer to the peak at 5 A than 2 A above or the start)."""
    env = _env(START, end_knobs="best")
    env.get_system_states()
    for shift in (4.0, 9.0):  # 9 A above overshoots the peak
        env.set_variables({k: v + shift for k, v in zip(SIM_KNOBS, START, strict=True)})
        env.get_observables(["loss_rate"])
    env.end_routine()
    assert env._epics.get().tolist() == [v + 4.0 for v in START]


def test_a_setting_outside_a_routine_starts_one():
    """A first set_variables without a start hook records the start first (a safety net)."""
    env = _env(START)
    env.set_variables({SIM_KNOBS[0]: 7.0})
    assert env.knobs_at_start == dict(zip(SIM_KNOBS, START, strict=True))
    env.end_routine()
    assert env._epics.get().tolist() == START


def test_sigterm_stops_a_routine_but_not_its_restore():
    """The SIGTERM handler raises Badger's BadgerRunTerminated during a routine and is silent
    once the routine is ending (so the restore is never interrupted)."""
    env = _env(START)
    env.reset_environment()
    with pytest.raises(BadgerRunTerminated):
        env._on_sigterm(15, None)
    env._ending = True
    env._on_sigterm(15, None)  # no exception


def test_end_knobs_is_validated():
    """end_knobs accepts only 'initial' and 'best'."""
    import pydantic

    with pytest.raises(pydantic.ValidationError):
        SimRingEnvironment(end_knobs="last")


def test_sigterm_during_an_evaluation_finishes_it_then_exits(monkeypatch):
    """A SIGTERM while the knobs are being set does not break the setting: it completes, the
    reading is taken, then the knobs are set back and only then the process is ended."""
    env = _env(START)
    env.reset_environment()
    machine = env._epics
    apply = machine._apply
    exits = []

    def apply_with_sigterm(x):
        env._on_sigterm(15, None)  # arrives in the middle of the setting
        apply(x)

    def exit_process(code):
        exits.append((code, machine.get().tolist()))

    machine._apply = apply_with_sigterm
    monkeypatch.setattr(SimRingEnvironment, "_exit_process", staticmethod(exit_process))
    target = [v + 1.0 for v in START]
    env.set_variables(dict(zip(SIM_KNOBS, target, strict=True)))
    assert machine.get().tolist() == target and not exits
    env.get_observables(["loss_rate"])
    assert exits == [(0, START)]  # the knobs were back when the process was ended
