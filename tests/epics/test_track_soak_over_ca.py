"""The soak: a track run of 10,000 readings over real Channel Access on a simulated IOC of its own
(127.0.0.1, refreshed every 10 ms: time compressed), with no growth of file descriptors
(``/proc/self/fd``), resident memory (RSS) or traced Python memory (tracemalloc) once the run is
warm. The run is built from a run file as ``pigp optimize`` builds it (``kind: epics``, the run
log with its hash chain and fsyncs, ramps, checked readings with the noise stated); the
optimizer is a tiny tracker whose own memory is bounded, so what is measured is the loop and the
CA client.
"""

from __future__ import annotations

import os
import time
import tracemalloc

import pytest
import torch

from pigp_torch.data.runlog import read_log
from pigp_torch.loop.run import RunSetup, build_machine, validate_config
from pigp_torch.loop.track_mode import KEEP_ROWS
from pigp_torch.optimizers.base import AskTellOptimizer

from .ca_runs import KNOBS

READINGS = 10_000
WARM = 2_000  # readings before the first sample: the kept rows (KEEP_ROWS) and caches are full
#: growth allowed from WARM to the end (8000 readings): a leak of one float per reading is 256 kB
#: of traced memory; RSS moves with the allocator's arenas, so its bound is looser
MAX_TRACED_GROWTH = 64 * 1024  # bytes
MAX_RSS_GROWTH = 4 * 1024  # kB


class Alternate(AskTellOptimizer):
    """Asks the start point ± 0.5 A in turn (every reading moves both knobs) and keeps the
    start and its last 5 readings only; tracks a made-up offset (A)."""

    name = "alternate"

    def ask(self) -> torch.Tensor:
        return self.X[0] + (0.5 if self.n_told % 2 else -0.5)

    def tell(self, x, y: float) -> None:
        super().tell(x, y)
        if len(self.Y) > 10:
            del self.X[1:-5], self.Y[1:-5]

    def tracked(self) -> dict[str, tuple[float, str]]:
        return {"offset": (0.1 * len(self.Y), "A")}


def fds() -> int:
    return len(os.listdir("/proc/self/fd"))


def rss_kb() -> int:
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmRSS"))


@pytest.mark.slow
def test_ten_thousand_readings_hold_the_same_descriptors_and_memory(tmp_path, monkeypatch):
    from pigp_torch.testing.ioc import start_sim_ioc

    monkeypatch.setenv("PIGP_LOCK_DIR", str(tmp_path / "locks"))
    data = {
        "machine": {"kind": "epics", "settle_time": 0.0, "timeout": 1.0, "stale_timeout": 1.0},
        "knobs": {k: [-15.0, 15.0] for k in KNOBS},
        "objective": {"pv": "SPEAR:BeamLossRate"},
        "method": {"name": "nelder-mead"},  # replaced by the tracker below
        "mode": "track",
        "time_limit": "30 min",  # a bound: the run must end by its count well before
        "budget": READINGS,
        "max_step": 0.2,
        "log": str(tmp_path / "soak.jsonl"),
        "objective_noise": 0.04,
    }
    samples: dict[int, tuple[int, int, int]] = {}

    def sample(row: dict) -> None:
        if row["step"] in (WARM, READINGS - 1):
            samples[row["step"]] = (fds(), rss_kb(), tracemalloc.get_traced_memory()[0])

    with start_sim_ioc(1, update_period=0.01) as ioc:
        data["objective"]["pv"] = ioc.loss_rate_pv
        config = validate_config(data)
        machine = build_machine(config)
        setup = RunSetup(config, Alternate(config.bounds()), machine)
        tracemalloc.start()
        t0 = time.monotonic()
        try:
            table = setup.run(log=config.log, callback=sample)
        finally:
            tracemalloc.stop()
            machine.close()
        elapsed = time.monotonic() - t0
    log = read_log(config.log)
    end = log.last_end
    assert end["reason"] == f"max_readings ({READINGS}) made", end["reason"]
    assert log.n_evaluations == READINGS == end["n_evaluations"] and len(table) == KEEP_ROWS
    assert end["restored_to"] == "estimate" and end["restored"] is True
    (fd0, rss0, traced0), (fd1, rss1, traced1) = samples[WARM], samples[READINGS - 1]
    print(f"soak: {READINGS} readings in {elapsed:.0f} s; from reading {WARM} to the last: "
          f"descriptors {fd0} -> {fd1}, RSS {rss0} -> {rss1} kB, traced {traced0} -> "
          f"{traced1} B")  # fmt: skip
    assert fd1 == fd0
    assert traced1 - traced0 <= MAX_TRACED_GROWTH
    assert rss1 - rss0 <= MAX_RSS_GROWTH
