"""Run files and starts shared by the tests that run ``pigp optimize`` over Channel Access."""

from __future__ import annotations

import pytest
import torch
import yaml

from pigp_torch import cli

KNOBS = ["01G-QSS4", "02G-QSS3"]


def bounds_of(ring, names=KNOBS) -> torch.Tensor:
    """Half the simulator's range for ``names`` (inside the IOC's control limits)."""
    idx = [list(ring.knob_names).index(n) for n in names]
    return ring.bounds[:, idx] / 2


def start_of(ring, names=KNOBS) -> torch.Tensor:
    """A nonzero start inside the bounds, so that a restore is visible."""
    b = bounds_of(ring, names)
    return b[1] * torch.tensor([0.2, -0.1][: len(names)], dtype=torch.float64)


def write_config(tmp_path, ioc, ring, name="run.yaml", **over) -> str:
    b = bounds_of(ring)
    data = {
        "machine": {"kind": "epics", "settle_time": 0.1, "timeout": 1.0, "stale_timeout": 1.0},
        "knobs": {k: [float(b[0, i]), float(b[1, i])] for i, k in enumerate(KNOBS)},
        "objective": {"pv": ioc.loss_rate_pv},
        "method": {"name": "nelder-mead", "options": {"initial_simplex_size": 0.5}},
        "budget": 6,
        "max_step": 0.2,
        "log": "run.jsonl",
        "retry_interval": 0.05,
        "restore_interval": 0.1,
        "restore_timeout": 0.0,  # the attempts only (a test of the window sets one)
    }
    data.update(over)
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data))
    return str(path)


@pytest.fixture(autouse=True)
def private_locks(tmp_path, monkeypatch):
    """Machine locks in this test's folder (not the host's shared one); import it into a test
    module to use it there."""
    monkeypatch.setenv("PIGP_LOCK_DIR", str(tmp_path / "locks"))


@pytest.fixture
def with_optimize(monkeypatch):
    """``pigp optimize`` among the CLI's commands (``cli.main(["optimize", ...])``)."""
    modules = tuple(dict.fromkeys((*cli.COMMAND_MODULES, "optimize")))
    monkeypatch.setattr(cli, "COMMAND_MODULES", modules)
