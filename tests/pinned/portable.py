r"""An environment in which the pinned math does not depend on the CPU's vector width.

A BO trajectory is chaotic: after one reading the acquisition is nearly flat over the trust box,
so a difference in the last bit of one reduction picks another maximizer and every later step
differs. The libraries choose their kernels by the CPU they find (AVX-512, AVX2, SSE), and kernels
of different widths sum in different orders, so bit-exact pins made on one CPU model fail on
another. This module names, for each library on the pinned path, the switch that selects one
code path on every x86-64 CPU:

===========================  ===========================  =================================
library                      variable                     effect
===========================  ===========================  =================================
PyTorch (ATen kernels)       ``ATEN_CPU_CAPABILITY``      ``default``: the scalar kernels
                                                          (and no SLEEF vector math)
Intel MKL (torch's BLAS and  ``MKL_CBWR``                 ``COMPATIBLE``: MKL's conditional
LAPACK)                                                   numerical reproducibility, the
                                                          SSE2 branch on any CPU
OpenBLAS (NumPy, SciPy)      ``OPENBLAS_CORETYPE``,       one named kernel set (Nehalem:
                             ``OPENBLAS_L2_SIZE``         SSE only) with fixed blocking
NumPy's own SIMD loops       ``NPY_DISABLE_CPU_FEATURES`` every dispatched target off: the
                                                          baseline loops only
glibc's libm (``exp``,       ``GLIBC_TUNABLES``           the FMA/AVX2 variants of the
``log``, ``pow`` ...)                                     elementary functions off
all of them                  ``*_NUM_THREADS`` = 1        no order set by a thread count
===========================  ===========================  =================================

The variables are read when each library initializes, so they only act on a NEW process:
:func:`run_portable` starts one. The cost is speed (scalar kernels), which the pinned runs,
13 knobs and at most 40 evaluations, can afford.

Checked by emulating other CPUs with QEMU's user-mode emulator (``qemu-x86_64 -cpu NAME``, which
shows the program another CPU's feature set): see ``tests/pinned/test_portable.py``.
"""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

#: Marks a process started by :func:`run_portable` (the pin module refuses to write pins outside).
MARKER = "PIGP_PORTABLE_NUMERICS"

#: glibc's x86 CPU features whose elementary-function variants are switched off.
_GLIBC_MASK = ("AVX2", "FMA", "FMA4", "AVX512F", "AVX512DQ", "AVX512VL", "AVX512BW")


def _numpy_dispatch_targets() -> str:
    """NumPy's dispatched SIMD targets of this build, as ``NPY_DISABLE_CPU_FEATURES`` wants them."""
    try:
        from numpy._core import _multiarray_umath as umath
    except ImportError:  # NumPy < 2
        from numpy.core import _multiarray_umath as umath
    return " ".join(umath.__cpu_dispatch__)


def portable_env(base: dict[str, str] | None = None) -> dict[str, str]:
    """A copy of ``base`` (default: ``os.environ``) with every switch of the table set."""
    env = dict(os.environ if base is None else base)
    env.update(
        {
            "ATEN_CPU_CAPABILITY": "default",
            "MKL_CBWR": "COMPATIBLE",
            "MKL_NUM_THREADS": "1",
            "OMP_NUM_THREADS": "1",
            "OPENBLAS_NUM_THREADS": "1",
            "OPENBLAS_CORETYPE": "Nehalem",
            "OPENBLAS_L2_SIZE": "512",
            "NPY_DISABLE_CPU_FEATURES": _numpy_dispatch_targets(),
            "GLIBC_TUNABLES": "glibc.cpu.hwcaps=" + ",".join("-" + f for f in _GLIBC_MASK),
            MARKER: "1",
        }
    )
    pythonpath = [str(ROOT), *filter(None, env.get("PYTHONPATH", "").split(os.pathsep))]
    env["PYTHONPATH"] = os.pathsep.join(dict.fromkeys(pythonpath))
    return env


def run_portable(
    args: Sequence[str],
    *,
    prefix: Sequence[str] = (),
    portable: bool = True,
    timeout: float = 1800.0,
) -> str:
    """Run ``python ARGS`` in a new process (under ``prefix``, e.g. an emulator) and return stdout.

    ``portable=False`` runs it in the unchanged environment (the comparison that shows why the
    switches are needed). Raises :class:`subprocess.CalledProcessError` with the child's stderr.
    """
    env = portable_env() if portable else dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.run(
        [*prefix, sys.executable, *args],
        env=env,
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
    )
    if proc.returncode != 0:
        raise subprocess.CalledProcessError(proc.returncode, proc.args, proc.stdout, proc.stderr)
    return proc.stdout
