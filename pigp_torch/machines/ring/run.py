r"""A run on the simulated ring (``machine: {kind: sim}``): its machine (:func:`build_ring_machine`:
the ring of the section behind a :class:`~pigp_torch.machine.SimulatedMachine` with the run's
bounds, noise, noise seed, step limit and start), as the ring kind gives it to the loop.
"""

from __future__ import annotations

import torch

from pigp_torch._utils import DTYPE
from pigp_torch.loop.config import ConfigError, RunConfig


class BoundedRing:
    """A simulated ring seen with the run's knob bounds (``2 x d``, the run's knob unit): the
    simulated machine takes its bounds from it; ``sim`` is the ring itself."""

    def __init__(self, sim, bounds: torch.Tensor) -> None:
        self.sim = sim
        self.bounds = bounds
        self.knob_names = list(sim.knob_names)

    def evaluate(self, x):
        return self.sim.evaluate(x)

    def __repr__(self) -> str:
        return f"{self.sim!r} within the run's bounds"


def simulated_ring(config: RunConfig):
    r"""The simulated ring of a ``kind: sim`` run: ``RingSpec.build(error_seed)`` of the section's
    :meth:`~.section.SimMachineConfig.ring_spec` — the SPEAR3 deck ``optics`` with
    the run's windings (:class:`~pigp_torch.machines.ring.spear3.Spear3Coupling`), or, with
    ``machine.lattice``, that lattice file with the run's knobs as element names
    (:class:`~pigp_torch.machines.ring.ring.RingCoupling`, calibration
    ``machine.knob_calibration``, range ``±machine.knob_limit`` in ``knob_unit``); with
    ``machine.loss_map: benchmark`` the loss-rate map that the benchmark gives machine
    ``error_seed`` (:func:`~pigp_torch.machines.ring.calibration.machine_loss_map` of the ring's
    own map).

    Raises:
        ConfigError: a knob name the lattice does not have, or a lattice file that does not load.
    """
    m = config.machine
    sim = _ring(config, None)
    if m.loss_map == "benchmark":
        from pigp_torch.machines.ring.calibration import machine_loss_map

        sim = _ring(config, machine_loss_map(m.error_seed, sim.loss_rate_map))
    return sim


def _ring(config: RunConfig, loss_rate_map):
    m = config.machine
    spec = m.ring_spec(config.knob_names, config.knob_unit)
    try:
        return spec.build(m.error_seed, loss_rate_map=loss_rate_map)
    except (OSError, ValueError, KeyError) as err:
        if spec.is_spear3:
            raise
        raise ConfigError(f"machine.lattice {m.lattice}: {err}") from err


def build_ring_machine(config: RunConfig):
    r"""The simulated machine of a ``kind: sim`` run: :func:`simulated_ring` behind a
    :class:`~pigp_torch.machine.SimulatedMachine` (reading noise ``machine.noise`` in the
    objective's unit, noise seed ``machine.seed``, the run's step limit) within the run's bounds,
    its knobs at ``machine.x_init`` (default 0, clipped to the bounds). Nothing is moved.

    Raises:
        ConfigError: a bound outside the simulator's knob range (the message gives the range in
            the run's knob unit), or the errors of :func:`simulated_ring`.
    """
    from pigp_torch.machine import SimulatedMachine

    names, bounds, m = config.knob_names, config.bounds(), config.machine
    sim = simulated_ring(config)
    outside = [
        n
        for n, lo, hi in zip(names, bounds[0].tolist(), bounds[1].tolist(), strict=True)
        if lo < float(sim.bounds[0, 0]) or hi > float(sim.bounds[1, 0])
    ]
    if outside:
        raise ConfigError(
            f"knobs {outside}: bounds outside the simulator's range "
            f"[{float(sim.bounds[0, 0]):g}, {float(sim.bounds[1, 0]):g}] {config.knob_unit}"
        )
    x_init = torch.tensor([(m.x_init or {}).get(n, 0.0) for n in names], dtype=DTYPE)
    x_init = torch.minimum(torch.maximum(x_init, bounds[0]), bounds[1])  # 0 may lie outside
    return SimulatedMachine(
        BoundedRing(sim, bounds),
        noise=m.noise,
        seed=m.seed,
        max_step=config.machine_max_step(),
        x_init=x_init,
    )
