r"""The loop's own machine section of a run file: a machine over EPICS Channel Access or pvAccess
(:class:`EpicsMachineConfig`). The sections of the simulated machines (``kind: sim``, the ring;
``kind: ares-sim``) are their kinds' (:meth:`pigp_torch.machines.MachineKind.section`); all are
chosen by ``kind`` (:data:`pigp_torch.loop.config.sections.MachineConfig`) and built of the strict
field types of :mod:`pigp_torch.machines.section` (:data:`Number`, :data:`Integer`, :data:`Flag`).
The run as a whole: :mod:`pigp_torch.loop.config.schema`.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from pigp_torch.machines.section import Flag as Flag  # re-exported for the schema
from pigp_torch.machines.section import Integer, Number, Section, resolve_path, same_knobs

#: the names the loop's modules have used (the building blocks live with the machine kinds)
_Section, _resolve, _same_knobs = Section, resolve_path, same_knobs


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
