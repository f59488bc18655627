r"""Machine kinds, one registry: :data:`KINDS` maps a name to the kind's plug-in
(:class:`~pigp_torch.machines.kind.MachineKind`), as :data:`pigp_torch.methods.METHODS` maps a
name to a method.

* ``spear3``: the SPEAR3 storage ring, or any ring given as a lattice file
  (:mod:`pigp_torch.machines.ring`): 13 skew windings (A), the loss rate and the emittances.
  ``KINDS["spear3"].model(error_seed=...)`` is its :class:`~pigp_torch.prior.MachineModel`.
* ``ares-ea``: the ARES-EA linac segment at DESY (:mod:`pigp_torch.machines.ares_ea`): five
  magnets and one screen. ``KINDS["ares-ea"].model(trial=...)`` is its
  :class:`~pigp_torch.prior.MachineModel`.

Drift and reality-gap families (machines whose hidden state changes with the reading count, or
that have physics their model lacks): ``KINDS[name].drift_families()`` and
``KINDS[name].drift_machine(family=..., seed=...)`` (docs/drift_families.md); the processes they
share are in :mod:`pigp_torch.machines.drift`.

A kind is one sub-package here whose ``__init__`` defines ``KIND``; nothing else is edited to add
one (docs/extending.md). Every kind passes the contract of
:mod:`pigp_torch.machines.contract`.
"""

from pigp_torch.machines.kind import KINDS, KindRegistry, MachineKind

__all__ = ["KINDS", "KindRegistry", "MachineKind"]
