"""Each machine kind's ``pigp`` commands, found through the registry: its top-level commands
(:meth:`~pigp_torch.machines.MachineKind.register_commands`: the ring's ``generate-data``,
``compare``, ``demo``, ``serve-sim``) and its ``pigp bench`` commands
(:meth:`~pigp_torch.machines.MachineKind.register_bench`: ``pigp bench ares``, ``pigp bench
simulator``, ``pigp bench spear3``). Registering imports only the kinds' light plug-ins and
parsers, so ``pigp --help`` stays torch-free."""

from __future__ import annotations


def register(sub, bench) -> None:
    """Add every machine kind's top-level commands to ``sub``, then every kind's ``pigp bench``
    commands to ``bench``."""
    from pigp_torch.machines import KINDS

    for kind in KINDS.values():
        kind.register_commands(sub)
    for kind in KINDS.values():
        kind.register_bench(bench)
