r"""``RingSpec``: which ring and knobs a simulated machine is, as plain, hashable data.

The benchmark, the error ensemble, the CLI and the simulated IOC build machines of one ring with
many error seeds; a :class:`RingSpec` says which ring (a shipped SPEAR3 deck, or any lattice
file), which knobs and their calibration, and :meth:`RingSpec.build` makes the machine of a seed.
It pickles (process pools, Dask) and serializes to JSON (:meth:`RingSpec.to_dict`, provenance).
"""

from __future__ import annotations

import dataclasses

from pigp_torch.machines.ring.ring import RingCoupling
from pigp_torch.machines.ring.spear3 import KNOB_LIMIT_A, Spear3Coupling


@dataclasses.dataclass(frozen=True)
class RingSpec:
    """A simulated ring and its knobs.

    Attributes:
        lattice: ``None`` for a shipped SPEAR3 deck (``optics``), else the path of a lattice file
            (our JSON element table, or any file ``at.load_lattice`` reads).
        optics: the SPEAR3 deck when ``lattice`` is ``None``: ``"user"`` (default), ``"design"``
            or ``"low_emittance"``.
        knobs: a SPEAR3 knob set (``"paper13"``, ``"powered14"``, ``"all72"``) or a tuple of knob
            names (SPEAR3 winding names, or element names of ``lattice``: ``FAM``, ``FAM[n]``,
            ``#i``).
        knob_calibration: K1s·L (1/m) per control unit, one value or one per knob; required with
            a ``lattice`` file, ignored for SPEAR3 (its windings' own calibration).
        knob_limit: symmetric bound of each knob (control units), default 30.
        knob_units: name of the control unit (default ``"A"``).
        loss_rate_map: ``(f_inf, g)`` of a ``lattice`` file's ring; default: calibrated on its
            error seed 1 (SPEAR3 uses its own constants).
    """

    lattice: str | None = None
    optics: str = "user"
    knobs: str | tuple = "paper13"
    knob_calibration: float | tuple | None = None
    knob_limit: float = KNOB_LIMIT_A
    knob_units: str = "A"
    loss_rate_map: tuple | None = None

    def __post_init__(self) -> None:
        for name in ("knobs", "knob_calibration", "loss_rate_map"):
            v = getattr(self, name)
            if v is not None and not isinstance(v, (str, int, float, tuple)):
                object.__setattr__(self, name, tuple(v))
        if isinstance(self.knob_calibration, tuple) and len(self.knob_calibration) == 1:
            object.__setattr__(self, "knob_calibration", float(self.knob_calibration[0]))
        if self.lattice is not None:
            object.__setattr__(self, "lattice", str(self.lattice))
            if isinstance(self.knobs, str):
                raise ValueError(
                    "with a lattice file, name the knobs (element names), not a SPEAR3 knob set"
                )
            if self.knob_calibration is None:
                raise ValueError("with a lattice file, give the knob calibration (K1s·L per unit)")
        if not float(self.knob_limit) > 0:
            raise ValueError(f"knob_limit must be positive, got {self.knob_limit}")

    @property
    def is_spear3(self) -> bool:
        """Whether this is a shipped SPEAR3 deck."""
        return self.lattice is None

    def build(self, error_seed: int, **kw) -> RingCoupling:
        """The machine of ``error_seed`` (a :class:`Spear3Coupling` for SPEAR3).

        Args:
            error_seed: the coupling-error seed.
            **kw: passed on (``target_ratio``, ``error_scale``, ``loss_rate_map`` to override
                this spec's).
        """
        kw.setdefault("loss_rate_map", self.loss_rate_map)
        if self.is_spear3:
            sim = Spear3Coupling(
                int(error_seed),
                knobs=self.knobs,
                optics=self.optics,
                knob_limit=float(self.knob_limit),
                **kw,
            )
        else:
            sim = RingCoupling(
                self.lattice,
                list(self.knobs),
                self.knob_calibration,
                knob_limit=float(self.knob_limit),
                knob_units=self.knob_units,
                error_seed=int(error_seed),
                **kw,
            )
        sim.spec = self
        return sim

    def describe(self, error_seed: int | None = None) -> str:
        """A one-line description for provenance records and progress output."""
        ring = f"SPEAR3 {self.optics}" if self.is_spear3 else self.lattice
        knobs = self.knobs if isinstance(self.knobs, str) else f"{len(self.knobs)} knobs"
        seed = "" if error_seed is None else f", error seed {int(error_seed)}"
        return f"{ring} ({knobs}, ±{self.knob_limit:g} {self.knob_units}{seed})"

    def to_dict(self) -> dict:
        """Plain JSON-able fields."""
        out = dataclasses.asdict(self)
        for k, v in out.items():
            if isinstance(v, tuple):
                out[k] = list(v)
        return out

    @classmethod
    def from_dict(cls, data: dict) -> RingSpec:
        """The inverse of :meth:`to_dict` (unknown keys are an error)."""
        fields = {f.name for f in dataclasses.fields(cls)}
        bad = set(data) - fields
        if bad:
            raise ValueError(f"unknown ring fields {sorted(bad)}")
        return cls(**data)


def knob_count(spec: RingSpec) -> int:
    """The number of knobs of ``spec`` without building the ring (a SPEAR3 knob set is resolved
    from its deck header)."""
    if not isinstance(spec.knobs, str):
        return len(spec.knobs)
    from pigp_torch.machines.ring.spear3 import knob_names_for

    return len(knob_names_for(spec.knobs, spec.optics))


#: the SPEAR3 user-mode ring with the 13 knobs of the study (the default everywhere)
SPEAR3 = RingSpec()


def as_ring_spec(ring=None, *, knobs=None) -> RingSpec:
    """``ring`` as a :class:`RingSpec`: ``None`` (SPEAR3, optionally with ``knobs``), a spec, or
    its :meth:`~RingSpec.to_dict` form."""
    if ring is None:
        return SPEAR3 if knobs is None else RingSpec(knobs=knobs)
    if isinstance(ring, dict):
        ring = RingSpec.from_dict(ring)
    if not isinstance(ring, RingSpec):
        raise TypeError(f"expected a RingSpec, got {type(ring).__name__}")
    if knobs is not None and knobs != ring.knobs:
        return dataclasses.replace(ring, knobs=knobs)
    return ring
