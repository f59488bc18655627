"""benchmarks/ask_time.py: the busy-loop children of the loaded pass end by themselves."""

from __future__ import annotations

import time

from tests.benchmark.conftest import load_script


def test_busy_children_end_by_themselves():
    script = load_script("ask_time")
    t0 = time.monotonic()
    children = script.busy_children(2, 0.5)
    assert len(children) == 2
    codes = [child.wait(timeout=30) for child in children]
    assert codes == [0, 0] and time.monotonic() - t0 >= 0.5
