"""Alias: the simulated EPICS servers (the ring as a Channel Access IOC and a pvAccess server,
for tests and demos) moved to :mod:`pigp_torch.simulated_epics`, a name that says what they are;
``pigp_torch.testing`` and each of its modules (``pigp_torch.testing.ioc``, ...) still import."""

from pigp_torch import simulated_epics as _moved
from pigp_torch._utils.aliases import alias_package

alias_package(__name__, _moved.__name__)

__all__ = list(_moved.__all__)
globals().update({name: getattr(_moved, name) for name in __all__})
