"""Alias: :mod:`pigp_torch.bench.scoring` under its old path (the module itself)."""

import sys

from pigp_torch.bench import scoring as _moved

sys.modules[__name__] = _moved
