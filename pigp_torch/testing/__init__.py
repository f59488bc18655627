"""Alias: the simulated EPICS servers' first path (they moved to ``pigp_torch.simulated_epics``,
then whole to the ring kind's folder, :mod:`pigp_torch.machines.ring.simulated_epics`);
``pigp_torch.testing`` and each of its modules (``pigp_torch.testing.ioc``, ... as the moved
module itself) still import."""

from pigp_torch._utils.aliases import alias_package

alias_package(__name__, "pigp_torch.simulated_epics", globals())
