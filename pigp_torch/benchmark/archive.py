"""Alias: :mod:`pigp_torch.bench.archive` under its old path (the module itself)."""

import sys

from pigp_torch.bench import archive as _moved

sys.modules[__name__] = _moved
