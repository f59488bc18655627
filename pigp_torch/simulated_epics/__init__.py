"""Alias: the simulated EPICS servers (the ring as a Channel Access IOC and a pvAccess server,
for tests and demos) moved whole to the ring kind's folder,
:mod:`pigp_torch.machines.ring.simulated_epics` (what they serve is the ring's);
``pigp_torch.simulated_epics`` and each of its modules (``pigp_torch.simulated_epics.ioc``, ...
as the moved module itself) still import, and so does the older ``pigp_torch.testing``."""

from pigp_torch._utils.aliases import alias_package

alias_package(__name__, "pigp_torch.machines.ring.simulated_epics", globals())
