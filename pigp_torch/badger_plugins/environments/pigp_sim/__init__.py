"""Badger environment ``pigp_sim``: the simulated SPEAR3 ring served by ``pigp serve-sim``, over
Channel Access (13 skew windings in amps, the loss rate in mA/min). The class lives in the
package, :class:`pigp_torch.badger_plugins.sim_ring.SimRingEnvironment` (parameters ``ca_port``,
``timeout`` and ``end_knobs``: the knobs found at the start of a routine are set back when it
ends or is aborted, however it is driven — also by Badger's own ``badger.core.run_routine`` in a
script, at the next routine, garbage collection or process exit — or ``best``), so that
upgrading pigp-torch upgrades this plugin."""

from pigp_torch.badger_plugins.sim_ring import SimRingEnvironment as Environment

__all__ = ["Environment"]
