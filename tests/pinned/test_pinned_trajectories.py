"""The registered methods' benchmark trajectories equal the pinned ones to the bit.

Each run is made in a new process on the CPU-independent path (tests/pinned/portable.py), so the
comparison to the bit holds on any x86-64 CPU.
"""

from __future__ import annotations

import json

import pytest

from tests.pinned.pin import DATA, RUNS, portable_trajectory, run_key

_PINNED = json.loads(DATA.read_text())


def _params():
    for i, run in enumerate(RUNS):
        marks = () if i < 2 else (pytest.mark.slow,)
        yield pytest.param(*run, id=run_key(*run), marks=marks)


@pytest.mark.parametrize("method, options, seed, budget", list(_params()))
def test_trajectory_is_pinned(method, options, seed, budget):
    pinned = _PINNED[run_key(method, options, seed, budget)]
    got = portable_trajectory(run_key(method, options, seed, budget))
    for step, (a, b) in enumerate(zip(got["X"], pinned["X"], strict=True)):
        assert a == b, f"step {step}: setting differs from the pinned one"
    assert got["y"] == pinned["y"]
    assert got["notice"] == pinned["notice"]
