"""Alias: :mod:`pigp_torch.bench.bo_speed` under its old path (the module itself)."""

import sys

from pigp_torch.bench import bo_speed as _moved

sys.modules[__name__] = _moved
