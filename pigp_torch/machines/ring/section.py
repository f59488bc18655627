r"""The ring's run-file section, ``machine: {kind: sim}`` (:class:`SimMachineConfig`): the
simulated SPEAR3 ring or any ring given as a lattice file, which the ring kind registers
(:meth:`~pigp_torch.machines.ring.RingKind.section`) and :func:`.run.build_ring_machine` builds.
Light (pydantic only): it is imported while the run-file schema is built.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Literal

from pydantic import Field, ValidationInfo, field_validator, model_validator

from pigp_torch.machines.section import Integer, Number, Section, resolve_path, same_knobs

if TYPE_CHECKING:
    from pigp_torch.machines.ring.spec import RingSpec


class SimMachineConfig(Section):
    r"""The simulated ring: :class:`~.spear3.Spear3Coupling` behind a
    :class:`~pigp_torch.machine.SimulatedMachine` with Gaussian reading noise; the ring is
    described by :meth:`ring_spec` (a :class:`~.spec.RingSpec`).

    The configured knobs are the simulator's skew windings (names like ``01G-QSS4``); their bounds
    must lie within the simulator's range (``±knob_limit``, default ±30 A).

    Any ring instead of SPEAR3: ``lattice`` names a lattice file (a JSON element table like those
    in ``pigp_torch/data``, or any file pyAT loads), the configured knobs are then element names
    of that lattice (``FAM``, ``FAM[n]``, ``#i``) and ``knob_calibration`` gives K1s·L (1/m) per
    knob unit (:class:`~.ring.RingCoupling`); the bounds must lie within
    ``±knob_limit``.

    Attributes:
        error_seed: error seed of the simulated machine.
        optics: the SPEAR3 deck, ``"user"`` (default), ``"design"`` or ``"low_emittance"``
            (without ``lattice``).
        noise: reading noise standard deviation (objective units, mA/min by default).
        seed: seed of the noise stream.
        x_init: knob values the machine starts at (unlisted knobs: 0).
        lattice: a lattice file (relative paths from the run file's folder); default ``None``:
            the shipped SPEAR3 deck ``optics``.
        knob_calibration: with ``lattice``: K1s·L (1/m) per knob unit, one value or
            ``{knob: value}`` for every knob (required with ``lattice``, refused without).
        knob_limit: the simulator's symmetric knob range (knob units, default 30: SPEAR3's
            ±30 A).
        loss_map: ``"model"`` (default): the ring's own loss-rate map (SPEAR3's constants);
            ``"benchmark"``: the map that the benchmark and ``pigp demo`` give machine
            ``error_seed`` (background and Touschek scale perturbed per seed,
            :func:`~.calibration.machine_loss_map`) — the same machine as the
            demo's "machine 1" for ``error_seed: 1``.
    """

    kind: Literal["sim"]
    error_seed: Integer = 1
    optics: Literal["user", "design", "low_emittance"] = "user"
    noise: Number = Field(0.04, ge=0.0)
    seed: Integer = 0
    x_init: dict[str, Number] | None = None
    lattice: Path | None = None
    knob_calibration: Number | dict[str, Number] | None = None
    knob_limit: Number = Field(30.0, gt=0.0)
    loss_map: Literal["model", "benchmark"] = "model"

    @field_validator("lattice")
    @classmethod
    def _resolve_lattice(cls, path: Path | None, info: ValidationInfo) -> Path | None:
        return resolve_path(path, info)

    @model_validator(mode="after")
    def _lattice_and_calibration(self) -> SimMachineConfig:
        if self.lattice is None and self.knob_calibration is not None:
            raise ValueError("knob_calibration goes with lattice (SPEAR3 has its own)")
        if self.lattice is not None and self.knob_calibration is None:
            raise ValueError("with a lattice file, give knob_calibration (K1s·L per knob unit)")
        cal = self.knob_calibration
        values = cal.values() if isinstance(cal, dict) else [] if cal is None else [cal]
        if any(not v > 0 for v in values):
            raise ValueError(f"knob_calibration must be positive, got {cal}")
        return self

    def check_knobs(self, names: list[str]) -> None:
        """``knob_calibration`` as a mapping names every knob of the run and no other."""
        if isinstance(self.knob_calibration, dict):
            same_knobs("machine.knob_calibration", self.knob_calibration, names)

    def ring_spec(self, knob_names: list[str], knob_unit: str = "A") -> RingSpec:
        r"""The simulated ring of this section as a :class:`~.spec.RingSpec`
        (the one description of a simulated ring; :meth:`RingSpec.build` makes the machine).

        Args:
            knob_names: the run's knobs, in order: SPEAR3 winding names, or with ``lattice``
                element names of that lattice.
            knob_unit: the run's knob unit (the lattice's control unit; SPEAR3's windings are
                in A whatever the run calls them).

        Returns:
            ``RingSpec(optics=optics, knobs=knob_names, knob_limit=knob_limit)`` for SPEAR3, or
            ``RingSpec(lattice, knob_names, calibration, knob_limit, knob_unit)`` with
            ``knob_calibration`` in knob order. The loss-rate map is left to the ring (the
            ``benchmark`` map depends on the built ring's own, see
            :func:`~pigp_torch.machines.ring.run.simulated_ring`).

        Raises:
            KeyError: ``knob_calibration`` is a mapping without one of ``knob_names``.
        """
        from pigp_torch.machines.ring.spec import RingSpec  # lazily: the simulator imports pyAT

        names = tuple(str(n) for n in knob_names)
        if self.lattice is None:
            return RingSpec(optics=self.optics, knobs=names, knob_limit=self.knob_limit)
        cal = self.knob_calibration
        cal = tuple(float(cal[n]) for n in names) if isinstance(cal, dict) else float(cal)
        return RingSpec(
            lattice=str(self.lattice),
            knobs=names,
            knob_calibration=cal,
            knob_limit=self.knob_limit,
            knob_units=knob_unit,
        )
