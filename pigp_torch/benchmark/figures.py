"""Alias: :mod:`pigp_torch.bench.figures` under its old path (the module itself)."""

import sys

from pigp_torch.bench import figures as _moved

sys.modules[__name__] = _moved
