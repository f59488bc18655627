"""Alias: :mod:`pigp_torch.bench.distributed` under its old path (the module itself)."""

import sys

from pigp_torch.bench import distributed as _moved

sys.modules[__name__] = _moved
