"""Packages renamed to say what they hold, or moved into the ring kind's folder, keep their old
paths: ``pigp_torch.testing`` and ``pigp_torch.simulated_epics`` (the simulated EPICS servers, now
``pigp_torch.machines.ring.simulated_epics``), ``pigp_torch.benchmark`` and ``pigp_torch.bench``
(the ring's "spear3-13" benchmark and demo, now ``pigp_torch.machines.ring.bench``; ``bench`` keeps
the BO speed run); every old module is the moved module itself."""

from __future__ import annotations

import importlib
import pkgutil
import subprocess
import sys

import pytest

import pigp_torch.bench
import pigp_torch.benchmark
import pigp_torch.machines.ring.bench
import pigp_torch.machines.ring.simulated_epics
import pigp_torch.simulated_epics
import pigp_torch.testing

RING_BENCH = pigp_torch.machines.ring.bench
RING_EPICS = pigp_torch.machines.ring.simulated_epics


@pytest.mark.parametrize(
    ("old", "moved", "kept"),
    [
        (pigp_torch.testing, RING_EPICS, []),
        (pigp_torch.simulated_epics, RING_EPICS, []),
        (pigp_torch.benchmark, RING_BENCH, ["ares"]),
        (pigp_torch.bench, RING_BENCH, ["bo_speed"]),
    ],
)
def test_every_module_keeps_its_old_path_as_the_same_module(old, moved, kept):
    """``<old>.<m>`` is ``<moved>.<m>`` (one module object: state and monkeypatches are
    shared), and the old package re-exports every public name of the moved one; a module the
    moved package lacks is not found at the old path either. At the old path stays only what
    did not move (``kept``: the ARES-EA benchmark's own alias, the BO speed run), so git sees the
    files as moved."""
    names = sorted(m.name for m in pkgutil.iter_modules(moved.__path__))
    assert len(names) >= 6
    olds = sorted(m.name for m in pkgutil.iter_modules(old.__path__))
    assert olds == kept
    for name in names:
        a = importlib.import_module(f"{old.__name__}.{name}")
        assert a is importlib.import_module(f"{moved.__name__}.{name}"), name
        assert a.__spec__.name == f"{moved.__name__}.{name}"  # its own spec, loaded once
    assert old.__all__ == moved.__all__
    assert all(getattr(old, n) is getattr(moved, n) for n in moved.__all__)
    with pytest.raises(ModuleNotFoundError):
        importlib.import_module(f"{old.__name__}.no_such_module")


def test_a_module_that_stayed_is_its_own():
    """``pigp_torch.bench.bo_speed`` (generic, not the ring's) stayed; its older path
    ``pigp_torch.benchmark.bo_speed`` is the same module, and nothing of the ring shadows it."""
    import pigp_torch.bench.bo_speed as speed

    assert speed.__spec__.name == "pigp_torch.bench.bo_speed"
    assert importlib.import_module("pigp_torch.benchmark.bo_speed") is speed
    assert not hasattr(RING_BENCH, "bo_speed")


def test_a_moved_module_patched_at_its_old_path_is_patched_everywhere(monkeypatch):
    """A monkeypatch through an old path (tests and outside checks do this) reaches the code
    that runs: the protocol's noise as ``pigp_torch.bench.protocol.NOISE`` is the ring's."""
    import pigp_torch.bench.protocol as old

    monkeypatch.setattr(old, "NOISE", 0.5)
    assert RING_BENCH.protocol.NOISE == 0.5
    assert importlib.import_module("pigp_torch.benchmark.protocol").NOISE == 0.5


def test_the_ares_benchmark_keeps_its_old_entry_points():
    """``pigp_torch.benchmark.ares`` re-exports the ARES-EA kind's benchmark functions."""
    pytest.importorskip("cheetah")
    from pigp_torch.benchmark.ares import run_ares_benchmark, run_ares_trial
    from pigp_torch.machines.ares_ea import benchmark

    assert run_ares_trial is benchmark.run_ares_trial
    assert run_ares_benchmark is benchmark.run_ares_benchmark


def test_the_old_module_path_still_runs_the_ioc_command():
    """``python -m pigp_torch.testing.ioc --help`` runs the moved module's command line."""
    out = subprocess.run(
        [sys.executable, "-m", "pigp_torch.testing.ioc", "--help"],
        capture_output=True, text=True, timeout=120, check=True,
    )  # fmt: skip
    assert "--update-period" in out.stdout
