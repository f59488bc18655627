"""Alias: :mod:`pigp_torch.bench.mismatch` under its old path (the module itself)."""

import sys

from pigp_torch.bench import mismatch as _moved

sys.modules[__name__] = _moved
