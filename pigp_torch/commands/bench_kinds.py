"""``pigp bench <kind>``: each machine kind's benchmark command, found through the registry
(:meth:`~pigp_torch.machines.MachineKind.register_bench`; ``pigp bench ares`` is ARES-EA's).
Registering imports only the kinds' light plug-ins, so ``pigp --help`` stays torch-free."""

from __future__ import annotations


def register(sub, bench) -> None:
    """Add every machine kind's ``pigp bench`` command to the ``pigp bench`` sub-parsers."""
    from pigp_torch.machines import KINDS

    for kind in KINDS.values():
        kind.register_bench(bench)
