"""Alias: the library behind ``pigp bench`` (the spear3-13 protocol, scoring, figures, the demo)
moved to :mod:`pigp_torch.bench`, beside which the top-level ``benchmarks/`` scripts no longer
share a name; ``pigp_torch.benchmark``, each of its modules (as the moved module itself) and
``pigp_torch.benchmark.ares`` (the ARES-EA benchmark, in its kind's folder) still import."""

from pigp_torch import bench as _moved
from pigp_torch._utils.aliases import alias_package

alias_package(__name__, _moved.__name__)

__all__ = list(_moved.__all__)
globals().update({name: getattr(_moved, name) for name in __all__})
