r"""The benchmark's machines: machine ``s`` of a ring with its own loss-rate map
(:func:`benchmark_ring`) and its true optimum :math:`f^*` (:func:`machine_optimum`, cached per
process), of the ``"project"`` family (default) or the ``"wide"`` one
(:mod:`~.families`). The protocol that runs methods on them:
:mod:`pigp_torch.machines.ring.bench.protocol`.
"""

from __future__ import annotations

from pigp_torch.machines.ring.bench.families import check_family, check_wide_ring, wide_machine
from pigp_torch.machines.ring.calibration import machine_loss_map
from pigp_torch.machines.ring.ring import RingCoupling
from pigp_torch.machines.ring.spec import RingSpec, as_ring_spec

_OPTIMA: dict[tuple, float] = {}


def _maps_key(machine_maps) -> bool | tuple[float, float]:
    """``machine_maps`` as a flag or a pair of factors (see :func:`benchmark_ring`)."""
    if isinstance(machine_maps, (tuple, list)):
        a, b = (float(v) for v in machine_maps)
        if not (a >= 0 and b > 0):
            raise ValueError(f"loss-map factors must be >= 0 and > 0, got {machine_maps}")
        return (a, b)
    return bool(machine_maps)


def benchmark_ring(
    machine_seed: int, ring: RingSpec, machine_maps=True, family: str = "project"
) -> RingCoupling:
    r"""Machine ``machine_seed`` of ``ring`` with its loss-rate map: ``True`` its own
    (:func:`machine_loss_map`), ``False`` the model's :math:`(f_\infty, g)`, or a pair of
    factors ``(a, b)``: :math:`(a f_\infty, b g)` for every machine (a map further off than the
    protocol's spread, e.g. a new vacuum chamber). The simulated ring only: the machine of a run
    file is built by :func:`pigp_torch.loop.run.build_machine`.

    ``family="wide"``: the machine of the wide family
    (:func:`~.families.wide_machine`: re-tuned deck, drawn error scale, peak
    and background); it draws its own map, so ``machine_maps`` must be ``True``.

    Raises:
        ValueError: an unknown family, or the wide family with another ring than the SPEAR3
            user deck or ``machine_maps`` not ``True``.
    """
    key = _maps_key(machine_maps)
    if check_family(family) == "wide":
        check_wide_ring(ring, key)
        return wide_machine(int(machine_seed), ring)
    sim = ring.build(int(machine_seed))
    if key is False:
        return sim
    if key is True:
        own = machine_loss_map(machine_seed, sim.loss_rate_map)
    else:
        own = (sim.loss_rate_map[0] * key[0], sim.loss_rate_map[1] * key[1])
    return ring.build(int(machine_seed), loss_rate_map=own)


def machine_optimum(
    machine_seed: int,
    n_starts: int = 8,
    *,
    knobs=None,
    ring: RingSpec | None = None,
    machine_maps=False,
    family: str = "project",
) -> float:
    """:math:`f^*` of machine ``machine_seed`` of ``ring`` (default SPEAR3; ``knobs`` overrides
    its knob set; with ``machine_maps`` its own loss-rate map; ``family`` as
    :func:`benchmark_ring`, the wide family with its own map whatever ``machine_maps`` says)
    from zero knobs and ``n_starts`` Sobol starts of L-BFGS-B
    (:meth:`~pigp_torch.machines.ring.ring.RingCoupling.optimum`); cached per process."""
    spec = as_ring_spec(ring, knobs=knobs)
    maps = True if check_family(family) == "wide" else _maps_key(machine_maps)
    key = (int(machine_seed), int(n_starts), spec, maps, family)
    if key not in _OPTIMA:
        sim = benchmark_ring(key[0], spec, maps, family)
        _OPTIMA[key] = float(sim.optimum(n_starts=key[1])[1])
    return _OPTIMA[key]
