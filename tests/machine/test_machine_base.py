"""Tests of the machine-boundary safety helpers: check_setting, max_step_tensor, ramp."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch

from pigp_torch.machine import GuardedMachine, Machine, check_setting, max_step_tensor, ramp

D = torch.float64
BOUNDS = torch.tensor([[-1.0, 0.0], [1.0, 4.0]], dtype=D)


class Recorder(GuardedMachine):
    """A guarded machine that records every applied setting and reads the first knob."""

    def __init__(self, **kwargs):
        super().__init__(BOUNDS, ["a", "b"], **kwargs)
        self.applied = []

    def _apply(self, x):
        self.applied.append(x.clone())

    def read(self):
        return float(self._x[0])


def test_max_step_scalar_is_a_fraction_of_the_half_range():
    """A scalar max_step s becomes s (h - l)/2 per knob; a d tensor is taken as absolute."""
    assert torch.equal(max_step_tensor(0.5, BOUNDS), torch.tensor([0.5, 1.0], dtype=D))
    absolute = torch.tensor([0.1, 0.2], dtype=D)
    assert torch.equal(max_step_tensor(absolute, BOUNDS), absolute)
    assert max_step_tensor(None, BOUNDS) is None
    for bad in (0.0, -1.0, float("nan"), [0.1, 0.2, 0.3]):
        with pytest.raises(ValueError, match="max_step"):
            max_step_tensor(bad, BOUNDS)


def test_check_setting_accepts_the_boundary_and_refuses_beyond():
    """Settings exactly on the bounds pass; beyond, wrong shapes, NaN or big steps raise."""
    assert torch.equal(check_setting([1.0, 0.0], BOUNDS), torch.tensor([1.0, 0.0], dtype=D))
    with pytest.raises(ValueError, match=r"knob indices \[1\]"):
        check_setting([0.0, 4.0001], BOUNDS)
    with pytest.raises(ValueError, match="shape"):
        check_setting([0.0, 1.0, 2.0], BOUNDS)
    with pytest.raises(ValueError, match="NaN"):
        check_setting([float("nan"), 1.0], BOUNDS)
    with pytest.raises(ValueError, match="single point"):
        check_setting(torch.zeros(2, 2), BOUNDS)
    limit = torch.tensor([0.1, 0.1], dtype=D)
    assert check_setting([0.1, 1.0], BOUNDS, current=[0.0, 1.05], max_step=limit)[0] == 0.1
    with pytest.raises(ValueError, match="step too large"):
        check_setting([0.2, 1.0], BOUNDS, current=[0.0, 1.0], max_step=limit)
    with pytest.raises(ValueError, match="current"):
        check_setting([0.0, 1.0], BOUNDS, max_step=limit)


def test_ramp_splits_a_move_into_allowed_steps():
    """ramp moves in ceil(max |delta|/max_step) equal steps, each allowed, ending on the target."""
    m = Recorder(max_step=torch.tensor([0.25, 1.0], dtype=D))
    target = torch.tensor([-0.9, 2.0], dtype=D)  # 0.9/0.25 = 3.6 -> 4 steps; 2/1 = 2
    assert ramp(m, target) == 4
    steps = torch.stack([torch.zeros(2, dtype=D), *m.applied])
    assert torch.equal(steps[-1], target)
    assert ((steps[1:] - steps[:-1]).abs() <= torch.tensor([0.25, 1.0], dtype=D) + 1e-15).all()
    unlimited = Recorder()
    assert ramp(unlimited, target) == 1 and torch.equal(unlimited.get(), target)


def test_guarded_machine_validation_and_protocol():
    """GuardedMachine checks names and the initial point; protocol checks need all members."""
    m = Recorder(x_init=[0.5, 3.0])
    assert isinstance(m, Machine) and m.read() == 0.5
    with pytest.raises(ValueError, match="outside bounds"):
        Recorder(x_init=[2.0, 0.0])
    with pytest.raises(ValueError, match="knob names"):
        GuardedMachine(BOUNDS, ["a"])
    with pytest.raises(ValueError, match="unique"):
        GuardedMachine(BOUNDS, ["a", "a"])
    partial = SimpleNamespace(knob_names=["a"], bounds=BOUNDS, set=print, get=list)
    assert not isinstance(partial, Machine)  # no read()
