"""Observables in the run log: what a machine measures besides its objective (a screen's beam
numbers) is kept with each evaluation, checked on read, told on replay; a log without them
reads and replays as before; the loop refuses an optimizer that fits observables on a machine
that has none."""

from __future__ import annotations

import pytest
import torch

from pigp_torch.data.runlog import RunLog, read_log, replay
from pigp_torch.loop import optimize
from pigp_torch.machine.base import GuardedMachine
from pigp_torch.optimizers.base import AskTellOptimizer

NAMES = ["mu_x", "sigma_x"]


def make_log(path, observables) -> None:
    header = {"knob_names": ["a"], "observable_names": NAMES, "observable_units": ["m", "m"]}
    with RunLog.create(path, header) as log:
        for k, obs in enumerate(observables):
            extra = {} if obs is None else {"observables": obs}
            log.log_evaluation(k, [0.1 * k], float(k), reads=1, **extra)


def test_observables_are_read_back_in_order_with_names_and_units(tmp_path):
    """Two evaluations with two observables each: ``observables()`` is the 2 x 2 table in step
    order, names and units from the header."""
    make_log(tmp_path / "r.jsonl", [[1e-3, 2e-5], [-4e-4, 3.5e-5]])
    log = read_log(tmp_path / "r.jsonl")
    assert log.observable_names == NAMES and log.observable_units == ["m", "m"]
    assert log.observables().tolist() == [[1e-3, 2e-5], [-4e-4, 3.5e-5]]


def test_a_log_without_observables_reads_as_before(tmp_path):
    """No observables logged (or only some): ``observables()`` is None, nothing else changes."""
    make_log(tmp_path / "r.jsonl", [None, [1.0, 2.0]])
    log = read_log(tmp_path / "r.jsonl")
    assert log.observables() is None and log.n_evaluations == 2


@pytest.mark.parametrize(
    ("obs", "message"),
    [
        ([1.0], "observables must be a list of 2 values"),
        ([1.0, True], "observables must be finite numbers"),
    ],
)
def test_malformed_observables_are_refused(tmp_path, obs, message):
    """Observables of the wrong length (the header names two) or not numbers: the reader names
    the line."""
    make_log(tmp_path / "r.jsonl", [obs])
    with pytest.raises(ValueError, match=rf"r.jsonl:2: {message}"):
        read_log(tmp_path / "r.jsonl")


class Recorder(AskTellOptimizer):
    """A minimal ask/tell optimizer that records what it is told."""

    def __init__(self, uses_observables: bool) -> None:
        super().__init__(torch.tensor([[-1.0], [1.0]], dtype=torch.float64))
        self.uses_observables = uses_observables
        self.told: list[tuple] = []

    def ask(self):
        return torch.tensor([0.1 * len(self.told)], dtype=torch.float64)

    def tell(self, x, y, observables=None):
        self.told.append((float(x[0]), y, None if observables is None else observables.tolist()))


def test_replay_tells_the_observables_to_an_optimizer_that_fits_them(tmp_path):
    """The logged observables reach ``tell(..., observables=)`` only where the optimizer says
    ``uses_observables``; another optimizer is told ``(x, y)``."""
    make_log(tmp_path / "r.jsonl", [[1.0, 2.0], [3.0, 4.0]])
    fits, plain = Recorder(True), Recorder(False)
    replay(fits, read_log(tmp_path / "r.jsonl"))
    replay(plain, read_log(tmp_path / "r.jsonl"))
    assert fits.told == [(0.0, 0.0, [1.0, 2.0]), (0.1, 1.0, [3.0, 4.0])]
    assert plain.told == [(0.0, 0.0, None), (0.1, 1.0, None)]


class Plain(GuardedMachine):
    """One knob, a reading and no observables."""

    def __init__(self) -> None:
        super().__init__(torch.tensor([[-1.0], [1.0]], dtype=torch.float64), ["a"])

    def _apply(self, x) -> None:
        pass

    def read(self) -> float:
        return float(self._x[0])


def test_an_optimizer_fitting_observables_needs_a_machine_that_has_them():
    """A run of an optimizer with ``uses_observables`` on a machine without
    ``last_observables`` is refused before anything moves."""
    machine = Plain()
    with pytest.raises(ValueError, match="fits the observables of each reading; this machine"):
        optimize(machine, Recorder(True), None, 3, handle_signals=False)
    out = optimize(machine, Recorder(False), None, 3, handle_signals=False)
    assert len(out) == 3
