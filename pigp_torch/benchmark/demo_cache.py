"""Alias: :mod:`pigp_torch.bench.demo_cache` under its old path (the module itself)."""

import sys

from pigp_torch.bench import demo_cache as _moved

sys.modules[__name__] = _moved
