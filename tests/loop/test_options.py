"""RunOptions: the loop's safety options, checked once when they are made."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from pigp_torch import optimize
from pigp_torch.loop import RunOptions
from pigp_torch.optimizers import NelderMead


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("restore", "somewhere", "restore must be one of"),
        ("read_retries", -1, "read_retries must be an integer >= 0"),
        ("retry_interval", float("nan"), "retry_interval must be finite"),
        ("objective_floor", float("inf"), "objective_floor must be finite or None"),
        ("readback_tol", -1e-3, "readback_tol must be finite"),
        ("restore_attempts", 0, "restore_attempts must be an integer >= 1"),
        ("restore_interval", float("inf"), "restore_interval must be finite"),
    ],
)
def test_bad_options_are_refused_when_made(field, value, message):
    with pytest.raises(ValueError, match=message):
        RunOptions(**{field: value})


def test_defaults_are_the_safe_choices_and_frozen():
    opts = RunOptions()
    assert (opts.restore, opts.read_retries, opts.restore_attempts) == ("initial", 2, 3)
    with pytest.raises(dataclasses.FrozenInstanceError):
        opts.restore = "none"


def test_there_is_no_move_mode_to_choose():
    """Every proposal is reached by the checked ramp: the former ``moves`` option is gone, and
    giving it is an error, not a silent no-op."""
    assert "moves" not in {f.name for f in dataclasses.fields(RunOptions)}
    with pytest.raises(TypeError, match="moves"):
        RunOptions(moves="set")


def test_keywords_override_the_options_object():
    """optimize(options=..., field=...) applies the keyword over the object: here the floor
    ends the run at its first reading."""
    bounds = torch.tensor([[-1.0, -1.0], [1.0, 1.0]], dtype=torch.float64)

    def f(x):
        return -float((x**2).sum())

    table = optimize(f, NelderMead(bounds), torch.zeros(2), 4, options=RunOptions())
    assert len(table) == 4
    with pytest.raises(RuntimeError, match="below the floor"):
        optimize(
            f,
            NelderMead(bounds),
            torch.full((2,), 0.5),
            4,
            options=RunOptions(objective_floor=None),
            objective_floor=0.0,
        )
    with pytest.raises(TypeError):
        optimize(f, NelderMead(bounds), torch.zeros(2), 4, no_such_option=1)
