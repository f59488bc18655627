"""benchmarks/early_losses.py: where a run loses evaluations, counted from its trace."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
import torch

from tests.benchmark.conftest import load_script


@pytest.fixture(scope="module")
def losses():
    return load_script("early_losses")


def _ask(x, centre, inform=False, half=1.0):
    """One logged ask in a 2-knob box of half-width ``half`` around zero."""
    lower, upper = torch.full((2,), -half), torch.full((2,), half)
    return {"x": torch.tensor(x), "centre": torch.tensor(centre), "lower": lower,
            "upper": upper, "inform": inform}  # fmt: skip


def test_counts_of_one_run(losses):
    """Budget 8: the reading at 95 % is evaluation 6, the fitted centre good after 4 readings."""
    gain = np.array([0.0, 0.2, 0.205, 0.208, 0.5, 0.96, 0.97, 0.99])
    g_centre = np.array([0.1, 0.3, 0.6, 0.96, 0.97, 0.98, 0.99])  # after 1..7 readings
    log = [
        _ask([1.0, 0.0], [2.0, 0.0]),  # on the edge, centre outside: clipped
        _ask([1.0, 0.0], [0.5, 0.0]),  # on the edge, centre inside: not clipped
        _ask([0.3, 0.2], [0.5, 0.0], inform=True),
        _ask([0.1, 0.0], [0.5, 0.0]),
        _ask([0.5, 0.0], [3.0, 0.0], inform=True),  # the ask of the reading at 95 %
        _ask([-1.0, 0.0], [-3.0, 0.0]),  # after it: not counted
        _ask([0.0, 0.0], [0.0, 0.0], inform=True),
    ]
    c = losses.count_losses(gain, g_centre, log, torch.ones(2), budget=8)
    assert (c["steps"], c["centre_at"], c["after"]) == (6, 4, 1)
    assert (c["clipped"], c["info"]) == (1, 2)
    assert c["stall"] == 2  # evaluations 3 and 4 rose by less than 0.01 over 0.2
    assert c["centre_gain_10"] != c["centre_gain_10"]  # past the budget: NaN
    never = losses.count_losses(np.zeros(8), np.zeros(7), log, torch.ones(2), budget=8)
    assert (never["steps"], never["centre_at"]) == (9, 9) and math.isnan(never["after"])
    assert never["stall"] == 7 and never["info"] == 3


def test_summary_medians_and_standard_errors(losses):
    counts = {"after": 0, "clipped": 0, "info": 3, "stall": 2}
    rows = [{"method": "m", "machine_seed": s, "steps": v, "centre_at": v - 1, **counts}
            for s, v in ((1, 10), (2, 20), (3, 60))]  # fmt: skip
    t = losses.summary(pd.DataFrame(rows))
    assert t.loc["m", "steps_median"] == 20.0
    se = np.std([10, 20, 60], ddof=1) / math.sqrt(3)
    assert t.loc["m", "steps_mean"] == f"30.0 ± {se:.1f}"
    assert t.loc["m", "machines"] == 3


def test_recording_keeps_the_run_and_logs_each_ask(losses):
    """The wrapped builder returns the same optimizer; each ask is logged with its info."""

    class Opt:
        def __init__(self):
            self.last_info = {}

        def ask(self):
            self.last_info = {"fitted_center": torch.ones(2), "trust_lower": -torch.ones(2),
                              "trust_upper": torch.ones(2), "inform": True}  # fmt: skip
            return torch.zeros(2)

    from pigp_torch.methods.registry import MethodSpec

    spec = MethodSpec(name="x", builder=lambda ctx, **o: Opt(), budget="gp")
    log = []
    opt = losses.recording(spec, log).build(None)
    assert torch.equal(opt.ask(), torch.zeros(2)) and torch.equal(opt.ask(), torch.zeros(2))
    assert len(log) == 2 and log[0]["inform"] and torch.equal(log[1]["centre"], torch.ones(2))


def test_refuses_the_reported_machines(losses):
    with pytest.raises(SystemExit, match="outside the benchmark's 1-24"):
        losses.main(["--prior", "p.json", "--seeds", "1-2", "default"])
