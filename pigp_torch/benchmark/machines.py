"""Alias: :mod:`pigp_torch.bench.machines` under its old path (the module itself)."""

import sys

from pigp_torch.bench import machines as _moved

sys.modules[__name__] = _moved
