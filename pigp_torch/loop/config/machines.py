r"""The machine sections of a run file: the simulated ring (:class:`SimMachineConfig`) and a
machine over EPICS Channel Access (:class:`EpicsMachineConfig`). The sections of the other machine
kinds (``kind: ares-sim``) are theirs (:meth:`pigp_torch.machines.MachineKind.section`); all are
chosen by ``kind`` (:data:`pigp_torch.loop.config.sections.MachineConfig`) and built of the strict
field types of :mod:`pigp_torch.machines.section` (:data:`Number`, :data:`Integer`,
:data:`Flag`). The run as a whole: :mod:`pigp_torch.loop.config.schema`.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Literal

from pydantic import Field, ValidationInfo, field_validator, model_validator

from pigp_torch.machines.section import Flag as Flag  # re-exported for the schema
from pigp_torch.machines.section import Integer, Number, Section, resolve_path

#: the names the loop's modules have used (the building blocks live with the machine kinds)
_Section, _resolve = Section, resolve_path

if TYPE_CHECKING:
    from pigp_torch.simulation.spec import RingSpec


# ------------------------------------------------------------------------------------ models
class SimMachineConfig(Section):
    r"""The simulated ring: :class:`~pigp_torch.simulation.Spear3Coupling` behind a
    :class:`~pigp_torch.machine.SimulatedMachine` with Gaussian reading noise; the ring is
    described by :meth:`ring_spec` (a :class:`~pigp_torch.simulation.spec.RingSpec`).

    The configured knobs are the simulator's skew windings (names like ``01G-QSS4``); their bounds
    must lie within the simulator's range (``±knob_limit``, default ±30 A).

    Any ring instead of SPEAR3: ``lattice`` names a lattice file (a JSON element table like those
    in ``pigp_torch/data``, or any file pyAT loads), the configured knobs are then element names
    of that lattice (``FAM``, ``FAM[n]``, ``#i``) and ``knob_calibration`` gives K1s·L (1/m) per
    knob unit (:class:`~pigp_torch.simulation.RingCoupling`); the bounds must lie within
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
            :func:`pigp_torch.bench.protocol.machine_loss_map`) — the same machine as the
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

    def ring_spec(self, knob_names: list[str], knob_unit: str = "A") -> RingSpec:
        r"""The simulated ring of this section as a :class:`~pigp_torch.simulation.spec.RingSpec`
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
        from pigp_torch.simulation.spec import RingSpec  # lazily: the simulator imports pyAT

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


class EpicsMachineConfig(Section):
    r"""A machine over EPICS Channel Access (:class:`pigp_torch.machine.epics.EpicsMachine`).

    PV names are ``setpoint_pvs[knob]`` (default ``knob + setpoint_suffix``) and
    ``readback_pvs[knob]`` (default ``knob + readback_suffix``); the objective PV is
    ``objective.pv``. The timing and averaging fields are passed to the machine. The readback
    tolerance is ``tolerance`` (knob units) or ``tolerance_fraction`` (of each knob's range);
    with neither, the machine's default (a millionth of the range: right for a simulated IOC,
    too tight for a real magnet's noisy readback). ``stale_timeout`` (s, default 10): how long
    a reading may wait for the objective PV's timestamp to advance. ``protocol``: ``ca``
    (Channel Access, :class:`~pigp_torch.machine.epics.EpicsMachine`, default) or ``pva``
    (pvAccess, :class:`~pigp_torch.machine.pva.PvaMachine`, the ``pva`` extra; the client is
    configured from ``EPICS_PVA_*`` in the environment). ``observable_pvs`` (``{name: PV}``,
    default none): what each reading also measures (e.g. a screen's beam numbers), read after
    the objective, logged with every evaluation and told to the methods that fit them;
    ``observable_units`` (``{name: unit}``) their units. ``refuse_severity`` (``INVALID``,
    default, or ``MAJOR``): a reading of the objective, a readback or an observable with this
    alarm severity or worse is not valid: it is read again and never becomes an evaluation.
    """

    kind: Literal["epics"]
    protocol: Literal["ca", "pva"] = "ca"
    setpoint_pvs: dict[str, str] | None = None
    readback_pvs: dict[str, str] | None = None
    setpoint_suffix: str = ":CurrSetpt"
    readback_suffix: str = ":Curr1"
    settle_time: Number = Field(0.5, ge=0.0)
    tolerance: Number | None = Field(None, gt=0.0)
    tolerance_fraction: Number | None = Field(None, gt=0.0, lt=1.0)
    n_average: Integer = Field(1, ge=1)
    average_interval: Number = Field(0.0, ge=0.0)
    timeout: Number = Field(2.0, gt=0.0)
    stale_timeout: Number = Field(10.0, gt=0.0)
    observable_pvs: dict[str, str] | None = None
    observable_units: dict[str, str] | None = None
    refuse_severity: Literal["MAJOR", "INVALID"] = "INVALID"

    @model_validator(mode="after")
    def _one_tolerance(self) -> EpicsMachineConfig:
        if self.tolerance is not None and self.tolerance_fraction is not None:
            raise ValueError("give tolerance (knob units) or tolerance_fraction, not both")
        pvs, units = self.observable_pvs, self.observable_units
        if pvs is not None:
            empty = [k for k, v in pvs.items() if not k.strip() or not v.strip()]
            if empty or not pvs:
                raise ValueError(f"machine.observable_pvs: give {{name: PV}}, got {pvs}")
        if units is not None and set(units) != set(pvs or {}):
            raise ValueError(
                f"machine.observable_units: name the unit of every observable of "
                f"observable_pvs {sorted(pvs or {})}, got {sorted(units)}"
            )
        return self
