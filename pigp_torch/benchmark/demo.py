"""Alias: :mod:`pigp_torch.bench.demo` under its old path (the module itself)."""

import sys

from pigp_torch.bench import demo as _moved

sys.modules[__name__] = _moved
