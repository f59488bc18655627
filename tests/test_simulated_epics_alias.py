"""The simulated EPICS servers live in ``pigp_torch.simulated_epics``; the old path
``pigp_torch.testing`` still imports, every module of it the moved module itself."""

from __future__ import annotations

import importlib
import pkgutil
import subprocess
import sys

import pigp_torch.simulated_epics as moved
import pigp_torch.testing as old


def test_every_module_keeps_its_old_path_as_the_same_module():
    """``pigp_torch.testing.<m>`` is ``pigp_torch.simulated_epics.<m>`` (one module object:
    state and monkeypatches are shared), and the package re-exports every public name."""
    names = sorted(m.name for m in pkgutil.iter_modules(moved.__path__))
    assert names == sorted(m.name for m in pkgutil.iter_modules(old.__path__))
    for name in names:
        a = importlib.import_module(f"pigp_torch.testing.{name}")
        assert a is importlib.import_module(f"pigp_torch.simulated_epics.{name}"), name
    assert old.__all__ == moved.__all__
    assert all(getattr(old, n) is getattr(moved, n) for n in moved.__all__)


def test_the_old_module_path_still_runs_the_ioc_command():
    """``python -m pigp_torch.testing.ioc --help`` runs the moved module's command line."""
    out = subprocess.run(
        [sys.executable, "-m", "pigp_torch.testing.ioc", "--help"],
        capture_output=True, text=True, timeout=120, check=True,
    )  # fmt: skip
    assert "--update-period" in out.stdout
