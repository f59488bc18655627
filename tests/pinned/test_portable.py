"""The pinned path gives the same bits on other CPUs, and the pins still catch a small change.

Other CPUs are emulated with QEMU's user-mode emulator: ``qemu-x86_64 -cpu NAME python ...`` runs
this Python, torch and NumPy on a CPU that reports NAME's features, so every library picks the
kernels it would pick there (Nehalem: SSE4.2 only, no FMA; EPYC-Rome: AVX2 + FMA, no AVX-512).
Those tests skip without the emulator (Debian's ``qemu-user``; ``.ci/run`` installs it).
"""

from __future__ import annotations

import json
import shutil

import pytest

from pigp_torch.methods import BO_DEFAULTS
from tests.pinned.pin import DATA, portable_trajectory

_PINNED = json.loads(DATA.read_text())
_KEY = "pigp-fast[]|101|30"
_QEMU = shutil.which("qemu-x86_64")
needs_qemu = pytest.mark.skipif(_QEMU is None, reason="qemu-x86_64 (Debian: qemu-user) not found")


def _first_difference(a: dict, b: dict) -> int | None:
    """The first evaluation whose setting differs (None: all equal)."""
    return next((i for i, (u, v) in enumerate(zip(a["X"], b["X"], strict=True)) if u != v), None)


@pytest.mark.slow
@needs_qemu
@pytest.mark.parametrize("cpu", ["Nehalem", "EPYC-Rome"])
def test_emulated_cpu_gives_the_pinned_bits(cpu):
    got = portable_trajectory(_KEY, prefix=(_QEMU, "-cpu", cpu))
    assert _first_difference(got, _PINNED[_KEY]) is None
    assert got["y"] == _PINNED[_KEY]["y"]


@pytest.mark.slow
@needs_qemu
def test_without_the_portable_path_an_emulated_cpu_differs():
    """The control: the same run in the unchanged environment depends on the CPU (so the switches
    are what makes the test above pass, not an insensitive comparison). EPYC-Rome, not Nehalem:
    an environment that names an AVX2 OpenBLAS kernel (``OPENBLAS_CORETYPE=Haswell``, set on some
    hosts) stops with an illegal instruction on an SSE-only CPU."""
    native = portable_trajectory(_KEY, portable=False)
    emulated = portable_trajectory(_KEY, prefix=(_QEMU, "-cpu", "EPYC-Rome"), portable=False)
    assert _first_difference(native, emulated) is not None


def test_a_1e_3_change_of_a_default_breaks_the_pin():
    """UCB's beta 0.1 % off its default: the pinned comparison fails within the run."""
    beta = BO_DEFAULTS["beta"] * (1 + 1e-3)
    got = portable_trajectory(("pigp-fast", {"beta": beta}, 101, 30))
    step = _first_difference(got, _PINNED[_KEY])
    assert step is not None and step < 30
