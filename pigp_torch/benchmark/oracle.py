"""Alias: :mod:`pigp_torch.bench.oracle` under its old path (the module itself)."""

import sys

from pigp_torch.bench import oracle as _moved

sys.modules[__name__] = _moved
