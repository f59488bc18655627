"""Fixtures of the Badger tests: a fresh HOME and a virtual environment layered on the running
one (so that ``pigp badger-setup`` writes its start-up file there, never into the shared one)."""

from __future__ import annotations

import os
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture
def layered_python(tmp_path) -> Path:
    """The python of a new venv whose site-packages comes first, then the running
    environment's (its .pth files processed, so editable installs work as in the parent)."""
    venv = tmp_path / "venv"
    subprocess.run(
        [sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True, timeout=120
    )
    python = venv / "bin" / "python"
    site = subprocess.run(
        [str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
        capture_output=True, text=True, check=True, timeout=60,
    ).stdout.strip()  # fmt: skip
    parent = sysconfig.get_paths()["purelib"]
    Path(site, "_parent_env.pth").write_text(f"import site; site.addsitedir({parent!r})\n")
    return python


@pytest.fixture
def fresh_home_env(tmp_path) -> dict[str, str]:
    """os.environ with HOME a new empty folder (no ~/.config), no XDG or EPICS_ settings, and
    this checkout on PYTHONPATH."""
    home = tmp_path / "home"
    home.mkdir()
    env = {k: v for k, v in os.environ.items() if not k.startswith(("EPICS_", "XDG_"))}
    env.update(HOME=str(home), QT_QPA_PLATFORM="offscreen", PYTHONPATH=str(REPO))
    return env
