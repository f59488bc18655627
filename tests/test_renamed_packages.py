"""Packages renamed to say what they hold keep their old paths: ``pigp_torch.testing`` (now
``pigp_torch.simulated_epics``, the simulated EPICS servers) and ``pigp_torch.benchmark`` (now
``pigp_torch.bench``, the library behind ``pigp bench``); every old module is the moved module
itself."""

from __future__ import annotations

import importlib
import pkgutil
import subprocess
import sys

import pytest

import pigp_torch.bench
import pigp_torch.benchmark
import pigp_torch.simulated_epics
import pigp_torch.testing


@pytest.mark.parametrize(
    ("old", "moved"),
    [
        (pigp_torch.testing, pigp_torch.simulated_epics),
        (pigp_torch.benchmark, pigp_torch.bench),
    ],
)
def test_every_module_keeps_its_old_path_as_the_same_module(old, moved):
    """``<old>.<m>`` is ``<moved>.<m>`` (one module object: state and monkeypatches are
    shared), and the old package re-exports every public name of the moved one; a module the
    moved package lacks is not found at the old path either."""
    names = sorted(m.name for m in pkgutil.iter_modules(moved.__path__))
    assert len(names) >= 6
    # nothing else stays at the old path (git sees the files as moved); benchmark.ares is the
    # ARES-EA benchmark's own alias
    olds = sorted(m.name for m in pkgutil.iter_modules(old.__path__))
    assert olds == (["ares"] if old is pigp_torch.benchmark else [])
    for name in names:
        a = importlib.import_module(f"{old.__name__}.{name}")
        assert a is importlib.import_module(f"{moved.__name__}.{name}"), name
        assert a.__spec__.name == f"{moved.__name__}.{name}"  # its own spec, loaded once
    assert old.__all__ == moved.__all__
    assert all(getattr(old, n) is getattr(moved, n) for n in moved.__all__)
    with pytest.raises(ModuleNotFoundError):
        importlib.import_module(f"{old.__name__}.no_such_module")


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
