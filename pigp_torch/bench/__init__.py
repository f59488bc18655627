"""The library behind ``pigp bench``: the BO speed run (:mod:`.bo_speed`, ``pigp bench bo``).

The "spear3-13" benchmark of the ring (the protocol, scoring, figures, the demo, its job runner)
moved to the ring kind's folder, :mod:`pigp_torch.machines.ring.bench` (``pigp bench spear3``);
its names here and each of its modules at its old path (``pigp_torch.bench.protocol``, ... as
the moved module itself) still import."""

from pigp_torch._utils.aliases import alias_package

alias_package(__name__, "pigp_torch.machines.ring.bench", globals())
