"""Alias: the first path of the library behind ``pigp bench`` (now :mod:`pigp_torch.bench`, the
BO speed run, and the ring's "spear3-13" benchmark in :mod:`pigp_torch.machines.ring.bench`);
``pigp_torch.benchmark``, its names and each of its modules (as the moved module itself) still
import, and so does ``pigp_torch.benchmark.ares`` (the ARES-EA benchmark, in its kind's folder)."""

from pigp_torch._utils.aliases import alias_package

alias_package(__name__, "pigp_torch.bench", globals())
