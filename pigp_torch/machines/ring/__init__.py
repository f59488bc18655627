r"""The storage-ring machine kind: SPEAR3 (the shipped decks, 13 skew windings in A) or any ring
given as a lattice file, its coupling tuned on the Touschek loss rate.

Everything ring-specific is in this folder:

* the simulation (the only importer of pyAT): the lattice decks (:mod:`.deck`, the element tables
  in ``data/`` with their provenance), lattices and knobs (:mod:`.lattice`), the seeded coupling
  errors (:mod:`.errors`), the fast batched differentiable model (:mod:`.linear_model`,
  :mod:`.lyapunov`), the pyAT reference path (:mod:`.reference`), the calibrations
  (:mod:`.calibration`), any ring (:class:`.ring.RingCoupling`) and SPEAR3 in amps
  (:class:`.spear3.Spear3Coupling`), a ring as plain data (:class:`.spec.RingSpec`), the error
  ensemble of optima (:mod:`.ensemble`) and the model's throughput (:mod:`.throughput`);
* the ring as a :class:`~pigp_torch.prior.machine_model.MachineModel` (:mod:`.model`), its drift
  families (:mod:`.drift`);
* its run-file section ``machine: {kind: sim}`` (:class:`.section.SimMachineConfig`) and the
  simulated machine built from it (:mod:`.run`);
* its benchmark, the "spear3-13" protocol, and ``pigp demo`` (:mod:`.bench`), its simulated EPICS
  servers (:mod:`.simulated_epics`), and its commands (:mod:`.commands`: ``pigp compare``,
  ``pigp bench spear3``, ``demo``, ``serve-sim``, ``generate-data``, ``bench simulator``);
* the plug-in :data:`KIND` that :data:`pigp_torch.machines.KINDS` lists as ``"spear3"``.

The old import paths (``pigp_torch.simulation``, ``pigp_torch.bench``, ``pigp_torch.benchmark``,
``pigp_torch.simulated_epics``, ``pigp_torch.testing``) are aliases of these modules. This module
imports nothing heavy (the registry imports it to find the kind).
"""

from __future__ import annotations

from typing import Any

from pigp_torch.machines.kind import MachineKind


class RingKind(MachineKind):
    r"""The ring kind: ``model(error_seed=0)`` is the model ring's
    :class:`~pigp_torch.prior.machine_model.MachineModel` (:func:`.model.ring_machine_model`),
    ``simulator(error_seed=1)`` a :class:`~pigp_torch.machines.ring.spear3.Spear3Coupling` (or, with
    ``ring``, a :class:`~pigp_torch.machines.ring.spec.RingSpec`'s ring)."""

    name = "spear3"
    run_file_kind = "sim"
    default_method = "pigp-physics"
    title = "SPEAR3 storage ring (or any lattice): skew windings, Touschek loss rate"

    def simulator(self, *, error_seed: int = 1, ring=None, **options: Any):
        r"""The simulated ring with error seed ``error_seed``: ``ring.build(error_seed,
        **options)`` of a :class:`~pigp_torch.machines.ring.spec.RingSpec`, default
        ``Spear3Coupling(error_seed, **options)`` (``knobs``, ``optics``, ``loss_rate_map``)."""
        if ring is not None:
            return ring.build(int(error_seed), **options)
        from pigp_torch.machines.ring.spear3 import Spear3Coupling

        return Spear3Coupling(int(error_seed), **options)

    def model(self, *, error_seed: int = 0, sim=None, coupling_half_width=None, **options: Any):
        r"""The machine model of the model ring ``sim`` (default :meth:`simulator` of
        ``error_seed``, default 0 as the benchmark's model; ``options`` go there), with
        coupling errors of half width ``coupling_half_width`` (control units, default a quarter
        of each knob's limit)."""
        from pigp_torch.machines.ring.model import ring_machine_model

        sim = self.simulator(error_seed=error_seed, **options) if sim is None else sim
        return ring_machine_model(sim, coupling_half_width)

    def section(self) -> type:
        from pigp_torch.machines.ring.section import SimMachineConfig

        return SimMachineConfig

    def simulated_machine(self, config):
        """The simulated ring of a ``kind: sim`` run file (:func:`.run.build_ring_machine`)."""
        from pigp_torch.machines.ring.run import build_ring_machine

        return build_ring_machine(config)

    def describe(self, config, machine) -> str:
        """The simulated ring: its deck or lattice file, error seed, loss-rate map, reading noise
        (the run's objective unit) and noise seed."""
        from pigp_torch._utils.units import display_unit

        m, (k, unit) = config.machine, display_unit(config.objective_unit)
        ring = f"SPEAR3 {m.optics}" if m.lattice is None else f"lattice {m.lattice}"
        maps = {"model": "the ring's loss-rate map", "benchmark": "the benchmark's loss-rate map"}
        return (
            f"simulated ring ({ring}, error seed {m.error_seed} with {maps[m.loss_map]}, noise "
            f"{k * m.noise:g} {unit}, noise seed {m.seed})"
        )

    def true_objective(self, config, say):
        """The simulated ring's noise-free loss rate (mA/min) and its noise; the report searches
        its maximum with the ring's differentiable loss rate."""
        from pigp_torch.machines.kind import TrueObjective

        say(f"building the simulated ring (error seed {config.machine.error_seed}) ...")
        machine = self.simulated_machine(config)
        ring = machine.sim.sim  # the ring behind the run's bounds (.run.BoundedRing)
        return TrueObjective(machine.true_value, float(config.machine.noise), ring.loss_rate)

    def methods_noise(self, section) -> None:
        """``None``: on the simulated ring the methods keep their own noise defaults (or the
        run file's ``method.options.noise``), as on a live ring."""
        return None

    def stated_noise(self, section) -> float | None:
        """The section's ``noise`` (mA/min) when above 0: the loop's re-read checks use it."""
        return section.noise if section.noise > 0 else None

    def benchmark(self, **options: Any):
        """The "spear3-13" benchmark (:func:`.bench.run_benchmark`)."""
        from pigp_torch.machines.ring.bench import run_benchmark

        return run_benchmark(**options)

    def register_commands(self, sub) -> None:
        """``pigp generate-data``, ``compare``, ``demo``, ``serve-sim`` (:mod:`.commands`)."""
        from pigp_torch.machines.ring.commands import register_commands

        register_commands(sub)

    def register_bench(self, bench) -> None:
        """``pigp bench simulator`` and ``pigp bench spear3`` (the same as ``pigp compare``)."""
        from pigp_torch.machines.ring.commands import register_bench

        register_bench(bench)

    def drift_families(self) -> dict[str, frozenset[str]]:
        """:data:`.drift.RING_FAMILIES`."""
        from pigp_torch.machines.ring.drift import RING_FAMILIES

        return dict(RING_FAMILIES)

    def drift_machine(self, *, family: str, seed: int = 101, **options: Any):
        r"""Machine ``seed`` (error seed, own loss-rate map) drifting as ``family``
        (:func:`.drift.ring_drift_machine`; ``options``: ``noise``, ``ring``, ``draw_seed``)."""
        from pigp_torch.machines.ring.drift import ring_drift_machine

        return ring_drift_machine(int(seed), family, **options)


#: The plug-in of this kind.
KIND = RingKind()
