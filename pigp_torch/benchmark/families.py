"""Alias: :mod:`pigp_torch.bench.families` under its old path (the module itself)."""

import sys

from pigp_torch.bench import families as _moved

sys.modules[__name__] = _moved
