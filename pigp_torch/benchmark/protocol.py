"""Alias: :mod:`pigp_torch.bench.protocol` under its old path (the module itself)."""

import sys

from pigp_torch.bench import protocol as _moved

sys.modules[__name__] = _moved
