"""ModelMachine: a machine model at true unknowns, read with noise."""

from __future__ import annotations

import pytest
import torch

from pigp_torch.machine.model_machine import ModelMachine
from tests.prior.test_machine_model import _offset_model

D = torch.float64
TARGET = torch.tensor([1.0, -2.0], dtype=D)


def _model():
    """Two knobs, two observables ``o = x + theta`` (mm), goal the squared distance to TARGET
    (the offset model of the machine-model tests with these parts)."""
    return _offset_model(
        bounds=torch.tensor([[-5.0, -5.0], [5.0, 5.0]], dtype=D),
        observable_names=["u", "v"],
        unknown_center=torch.zeros(2, dtype=D),
        unknown_half_width=torch.ones(2, dtype=D),
        observe=lambda X, th: X + th,
        goal=lambda O: (O - TARGET).square().sum(-1),
    )


def test_a_reading_is_the_goal_of_the_model_at_the_true_unknowns():
    theta = torch.tensor([0.5, 0.25], dtype=D)
    m = ModelMachine(_model(), theta)
    assert m.get().tolist() == [0.0, 0.0]  # the middle of the bounds
    m.set(torch.tensor([1.0, 2.0], dtype=D))
    assert m.read() == pytest.approx((1.5 - 1.0) ** 2 + (2.25 + 2.0) ** 2)
    assert m.last_observables.tolist() == [1.5, 2.25]
    assert m.observable_names == ("u", "v") and m.observable_units == ("mm", "mm")
    assert m.knob_units == ("A", "A")
    maximized = ModelMachine(_model(), theta, maximize=True, x_init=torch.tensor([1.0, 2.0]))
    assert maximized.read() == pytest.approx(-((0.5) ** 2 + 4.25**2))


def test_noise_is_seeded_and_advance_noise_moves_the_stream_as_readings_do():
    theta = torch.zeros(2, dtype=D)
    a = ModelMachine(_model(), theta, noise=0.1, seed=4)
    b = ModelMachine(_model(), theta, noise=0.1, seed=4)
    first = [a.read() for _ in range(3)]
    assert first == [b.read() for _ in range(3)]
    assert len(set(first)) == 3  # noisy
    c = ModelMachine(_model(), theta, noise=0.1, seed=4)
    c.advance_noise(3)
    assert c.read() == a.read()
    sd = torch.stack([a.read_observables() for _ in range(2000)]).std(0)
    torch.testing.assert_close(sd, torch.full((2,), 0.1, dtype=D), rtol=0.05, atol=0.0)


def test_settings_are_guarded_and_bad_arguments_refused():
    m = ModelMachine(_model(), torch.zeros(2), max_step=0.1)
    with pytest.raises(ValueError, match="outside bounds"):
        m.set(torch.tensor([6.0, 0.0], dtype=D))
    with pytest.raises(ValueError, match="step"):
        m.set(torch.tensor([2.0, 0.0], dtype=D))  # a step over 10 % of the half-range
    assert m.get().tolist() == [0.0, 0.0]
    with pytest.raises(ValueError, match="2 unknowns"):
        ModelMachine(_model(), torch.zeros(3))
    with pytest.raises(ValueError, match="noise"):
        ModelMachine(_model(), torch.zeros(2), noise=-1.0)
