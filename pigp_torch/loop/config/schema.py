r"""Run files of ``pigp optimize``: the schema (pydantic models) of a run configuration.

A run file (YAML or JSON) names everything a run on a machine needs; it is validated as a whole
(pydantic v2, unknown keys refused) before anything is connected or moved::

    machine:                      # sim: the simulated SPEAR3 ring; epics: Channel Access;
                                  # ares-sim: the simulated ARES-EA linac (a published trial)
      kind: sim
      error_seed: 1
      noise: 0.04                 # mA/min
      # lattice: my_ring.json     # any ring: a lattice file, knobs = its element names,
      # knob_calibration: 5.15e-4 #   K1s·L (1/m) per knob unit
    knobs:                        # name: [lower, upper], in knob units (amperes of the windings)
      01G-QSS4: [-30, 30]
      02G-QSS3: [-30, 30]
    objective: {maximize: true}   # epics: {pv: SPEAR:BeamLossRate, maximize: true}
    method: {name: nelder-mead, options: {initial_simplex_size: 0.05}}
    prior: prior.json             # a PhysicsPrior file (needed by pigp), knobs must match, or
                                  # builtin:spear3, the SPEAR3 prior shipped with the package
    budget: 60
    max_step: 0.1                 # required: fraction of each knob's half-range, {knob: value},
                                  # or the word unlimited (no step limit, deliberately)
    log: runs/sim.jsonl           # the run log (JSON lines)
    restore: initial              # or best (set the best observed point at the end), current
    # mode: track                 # keep it tuned until stopped: pigp_torch.loop.config.track
    # time_limit: 8 h             #   (the track keys: time_limit, restore: estimate, best_window)
    restore_timeout: 30           # s the restore keeps trying (a stall, an IOC restart)
    read_retries: 2
    # objective_noise: 0.04       # one reading's noise; epics without it: measured at the
    # noise_reads: 5              #   start from this many readings at the initial setting
    objective_floor: null         # abort when a reading falls below this
    objective_unit: mA/min        # units printed and drawn with the numbers (these defaults)
    knob_unit: A

Relative paths (``prior``, ``log``, ``lock_dir``) are taken relative to the run file's folder.

A key given twice in a file is an error (YAML and JSON alike), not "the last one wins".
``max_step`` has no default: a number, a per-knob mapping, or the word ``unlimited``; ``null``
is refused. A fraction above 1 (more than a whole half-range of each knob per set), or a
per-knob limit above half that knob's range, is refused: the one way to run without a step limit
is to write ``unlimited``. :meth:`RunConfig.warnings` names every step limit above 10 % of its
knob's range (``pigp optimize`` prints them).

Numbers must be numbers (pydantic strict mode): ``true``/``false`` or a quoted ``"0.5"`` where a
number belongs (bounds, limits, timings, seeds, the budget) is refused, not converted; an integer
field takes no ``5.0``; ``maximize`` takes ``true`` or ``false`` only.

``method.name`` is one of the methods that run files accept (``pigp``, ``pigp-fast``,
``pigp-physics``, ``ml2``, ``nelder-mead``, ``rcds``, and on ``kind: ares-sim`` also
``ares-physics``, ``published-bo``, ``published-nm``; :mod:`pigp_torch.methods` describes them)
and ``method.options`` are its builder's options. This module checks the file's structure only;
the method, its options and the prior file are checked against the method registry by
:func:`pigp_torch.loop.run.validate_config` (which ``pigp optimize`` calls).

Every error is reported at once, one line per problem, as a :class:`ConfigError` (a
``ValueError``) naming the key: a wrong key, a missing PV name, bounds with lower >= upper.
"""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from pydantic import (
    Field,
    PrivateAttr,
    ValidationInfo,
    field_validator,
    model_validator,
)

from pigp_torch.data import BUILTIN_PREFIX, builtin_prior
from pigp_torch.loop.config.machines import (
    EpicsMachineConfig,
    Flag,
    Integer,
    Number,
    _resolve,
    _same_knobs,
    _Section,
)
from pigp_torch.loop.config.sections import MachineConfig
from pigp_torch.loop.config.track import check_mode, duration_s

if TYPE_CHECKING:
    import torch


class ConfigError(ValueError):
    """An invalid run configuration (the message lists every problem, one per line)."""


#: Largest ``max_step`` fraction a run file may give: one half-range of each knob per set.
MAX_STEP_FRACTION = 1.0


class ObjectiveConfig(_Section):
    """What is optimized: ``pv`` (EPICS only) and the direction."""

    pv: str | None = None
    maximize: Flag = True


class MethodConfig(_Section):
    """The optimizer: ``name`` (a run-file method of :mod:`pigp_torch.methods`, checked by
    :func:`pigp_torch.loop.run.validate_config`), its ``options`` and its ``seed`` (BayesOpt's
    per-ask seed; Nelder–Mead and RCDS are deterministic)."""

    name: str
    seed: Integer = 0
    options: dict[str, Any] = Field(default_factory=dict)


class RunConfig(_Section):
    r"""A validated ``pigp optimize`` run (see the module docstring for the file format).

    Attributes:
        machine: :class:`EpicsMachineConfig` or a machine kind's section (``sim``: the
            ring's, ``ares-sim``), by ``kind`` (:mod:`~pigp_torch.loop.config.sections`).
        knobs: ``{name: (lower, upper)}`` in knob order.
        objective: :class:`ObjectiveConfig`.
        method: :class:`MethodConfig`.
        prior: a :class:`~pigp_torch.prior.PhysicsPrior` JSON file (required by the methods
            built from the physics prior), or ``builtin:NAME``, a prior shipped with the package
            (:data:`pigp_torch.data.BUILTIN_PRIORS`: ``builtin:spear3``, the 13 windings).
        budget: evaluations, the start point included.
        max_step: largest change of a knob per ``set`` (required): a fraction of each knob's
            half-range, ``{knob: absolute}``, or ``"unlimited"`` (no step limit).
        log: the run log to write.
        restore: ``"initial"`` (put the knobs back), ``"best"`` (set the best observed point),
            ``"current"`` (leave them), or in a track run ``"estimate"`` (its default).
        mode: ``"optimize"`` (default: ``budget`` evaluations) or ``"track"`` (until stopped,
            ``time_limit`` or ``budget`` readings: :mod:`~pigp_torch.loop.config.track`).
        time_limit: a track run's wall-clock limit, a number and a unit (``"8 h"``).
        best_window: a track run's ``restore: best`` picks among this many last readings.
        read_retries: extra read attempts after an invalid reading (the loop's; the EPICS
            machine is given none of its own, so this is the total).
        retry_interval: seconds before each extra read attempt.
        objective_floor: abort when a reading falls below this (``None``: no floor).
        objective_range: ``[lower, upper]`` physical range of a reading; one outside is
            discarded and read again (``None``: the objective PV's DRVL/DRVH or LOPR/HOPR).
        objective_noise: noise (standard deviation) of one reading, objective units; a reading
            far from the run's own (and the first) is then re-read and kept only if it
            repeats (``None``: the simulated machine's noise, else the prior's; on
            ``kind: epics`` with neither, measured at the start: ``noise_reads``).
        noise_reads: readings taken at the initial setting before the first evaluation, on
            ``kind: epics`` when no noise is stated, whose standard deviation (at least 1 % of
            their mean) is then the noise (default 5, 3 to 50; a resume reuses the logged one).
        readback_tolerance: allowed readback error after the final set, a fraction of the range.
        restore_attempts: attempts at restoring the knobs at the end (default 3).
        restore_interval: seconds between those attempts (default 1).
        restore_timeout: the restore's window, seconds (default 30, at most 3600): attempts go
            on until ``restore_attempts`` were made and this long has passed since the first, so
            a network stall or an IOC restart shorter than it still ends restored.
        lock_dir: folder of the machine locks (default ``$PIGP_LOCK_DIR`` or
            ``<tmp>/pigp-locks``; see :mod:`pigp_torch.data.runlock`).
        objective_unit: unit of the objective's readings, printed and drawn with every number
            (default ``"mA/min"``, the SPEAR3 loss rate).
        knob_unit: unit of the knob values and bounds (default ``"A"``, winding currents).
    """

    machine: MachineConfig
    knobs: dict[str, tuple[Number, Number]]
    objective: ObjectiveConfig = Field(default_factory=ObjectiveConfig)
    method: MethodConfig
    prior: Path | None = None
    budget: Integer = Field(ge=1)
    max_step: Number | dict[str, Number] | Literal["unlimited"]
    log: Path
    restore: Literal["initial", "best", "current", "estimate"] | None = None
    mode: Literal["optimize", "track"] = "optimize"
    time_limit: str | None = None
    best_window: Integer = Field(20, ge=1, le=100_000)
    read_retries: Integer = Field(2, ge=0)
    retry_interval: Number = Field(0.1, ge=0.0)
    objective_floor: Number | None = None
    objective_range: tuple[Number, Number] | None = None
    objective_noise: Number | None = Field(None, gt=0.0)
    noise_reads: Integer = Field(5, ge=3, le=50)
    readback_tolerance: Number = Field(1e-3, ge=0.0)
    restore_attempts: Integer = Field(3, ge=1, le=100)
    restore_interval: Number = Field(1.0, ge=0.0)
    restore_timeout: Number = Field(30.0, ge=0.0, le=3600.0)
    lock_dir: Path | None = None
    objective_unit: str = Field("mA/min", min_length=1)
    knob_unit: str = Field("A", min_length=1)

    _prior = PrivateAttr(default=None)

    @field_validator("max_step", mode="before")
    @classmethod
    def _explicit_max_step(cls, value):
        if value is None:
            raise ValueError(
                "null is not a step limit: give a fraction of each knob's half-range (e.g. 0.1), "
                "a {knob: value} mapping, or write unlimited to run without a step limit"
            )
        if isinstance(value, bool) or (isinstance(value, str) and value != "unlimited"):
            raise ValueError(
                f"{value!r} is not a step limit: give a number, a {{knob: value}} mapping, or "
                "the word unlimited (no step limit)"
            )
        if isinstance(value, float) and not math.isfinite(value):
            raise ValueError(
                f"{value} is not a step limit: give a finite fraction of each knob's half-range "
                "(e.g. 0.1), or write unlimited to run without a step limit"
            )
        return value

    @field_validator("knobs")
    @classmethod
    def _check_knobs(cls, knobs: dict[str, tuple[float, float]]):
        if not knobs:
            raise ValueError("at least one knob is needed")
        for name, (lo, hi) in knobs.items():
            if not name.strip():
                raise ValueError("knob names must not be empty")
            if not lo < hi:
                raise ValueError(f"knob {name!r}: lower bound {lo} must be below upper bound {hi}")
        return knobs

    @field_validator("prior", "log", "lock_dir")
    @classmethod
    def _resolve_paths(cls, path: Path | None, info: ValidationInfo) -> Path | None:
        if info.field_name == "prior" and str(path).startswith(BUILTIN_PREFIX):
            return builtin_prior(str(path))  # a prior shipped with the package
        return _resolve(path, info)

    @model_validator(mode="after")
    def _check_run(self) -> RunConfig:
        self.restore = check_mode(self.mode, self.time_limit, self.restore)
        names = list(self.knobs)
        rng = self.objective_range
        if rng is not None and not rng[0] < rng[1]:
            raise ValueError(f"objective_range: lower {rng[0]} must be below upper {rng[1]}")
        if isinstance(self.max_step, dict):
            _same_knobs("max_step", self.max_step, names)
            bad = [k for k, v in self.max_step.items() if not v > 0]
            if bad:
                raise ValueError(f"max_step: the limits of {bad} must be positive")
            big = [
                f"{k} {v:g} > {(self.knobs[k][1] - self.knobs[k][0]) / 2:g}"
                for k, v in self.max_step.items()
                if v > (self.knobs[k][1] - self.knobs[k][0]) / 2
            ]
            if big:
                raise ValueError(
                    f"max_step: the limits of {', '.join(big)} exceed half the knob's range (a "
                    "whole half-range per set); write max_step: unlimited to run without a "
                    "step limit on purpose"
                )
        elif isinstance(self.max_step, float) and not self.max_step > 0:
            raise ValueError(f"max_step must be positive (or unlimited), got {self.max_step}")
        elif isinstance(self.max_step, float) and self.max_step > MAX_STEP_FRACTION:
            raise ValueError(
                f"max_step {self.max_step:g} is above {MAX_STEP_FRACTION:g}: more than a whole "
                "half-range of each knob per set (max_step is a fraction of each knob's "
                "half-range); write max_step: unlimited to run without a step limit on purpose"
            )
        m = self.machine
        m.check_knobs(names)  # the section's own knob-keyed fields
        if not isinstance(m, EpicsMachineConfig):  # a simulated machine
            if self.objective.pv is not None:
                raise ValueError("objective.pv is for the epics machine; the sim reads its model")
            for name, value in (getattr(m, "x_init", None) or {}).items():  # a kind may have none
                if name not in self.knobs:
                    raise ValueError(f"machine.x_init: {name!r} is not a configured knob")
                lo, hi = self.knobs[name]
                if not lo <= value <= hi:
                    raise ValueError(f"machine.x_init: {name} = {value} lies outside [{lo}, {hi}]")
        else:
            if not (self.objective.pv or "").strip():
                raise ValueError("objective.pv: the epics machine needs the objective's PV name")
            for key in ("setpoint_pvs", "readback_pvs"):
                pvs = getattr(m, key)
                if pvs is not None:
                    _same_knobs(f"machine.{key}", pvs, names, what="no PV name for knobs")
                    empty = [k for k, v in pvs.items() if not v.strip()]
                    if empty:
                        raise ValueError(f"machine.{key}: empty PV name for knobs {empty}")
        return self

    # -- derived values ---------------------------------------------------------------------------
    @property
    def knob_names(self) -> list[str]:
        return list(self.knobs)

    def time_limit_s(self) -> float | None:
        """A track run's wall-clock limit in s (``None`` in a one-shot run)."""
        return None if self.time_limit is None else duration_s(self.time_limit)

    def bounds(self) -> torch.Tensor:
        """``2 x d`` knob bounds in knob order."""
        import torch  # here, not at the top: validating a run file does not load torch

        from pigp_torch._utils import DTYPE

        return torch.tensor(list(zip(*self.knobs.values(), strict=True)), dtype=DTYPE)

    def machine_max_step(self) -> float | torch.Tensor | None:
        """``max_step`` as the machines take it: a fraction, a ``d`` absolute tensor, or
        ``None`` (unlimited)."""
        if isinstance(self.max_step, dict):
            import torch

            from pigp_torch._utils import DTYPE

            return torch.tensor([self.max_step[n] for n in self.knobs], dtype=DTYPE)
        if self.max_step == "unlimited":
            return None
        return self.max_step

    def warnings(self) -> list[str]:
        """Safety warnings (no error): no step limit, or a knob's limit above 10 % of its
        range (one line naming every such knob)."""
        if self.max_step == "unlimited":
            return ["max_step: unlimited: no step limit, a proposal is reached in one set"]
        from pigp_torch._utils import max_step_tensor

        bounds = self.bounds()
        width = bounds[1] - bounds[0]
        limit = max_step_tensor(self.machine_max_step(), bounds)
        big = [
            f"{n} {float(limit[i]):.4g} ({100 * float(limit[i] / width[i]):.0f} %)"
            for i, n in enumerate(self.knobs)
            if float(limit[i]) > 0.1 * float(width[i])
        ]
        if not big:
            return []
        return [f"max_step above 10 % of the knob's range: {', '.join(big)}"]

    def pv_names(self) -> list[str]:
        """Every PV the run uses (setpoints, readbacks, objective, observables); empty for the
        simulators."""
        m = self.machine
        if not isinstance(m, EpicsMachineConfig):
            return []
        names = self.knob_names
        sp = m.setpoint_pvs or {n: f"{n}{m.setpoint_suffix}" for n in names}
        rb = m.readback_pvs or {n: f"{n}{m.readback_suffix}" for n in names}
        obs = list((m.observable_pvs or {}).values())
        return [*(sp[n] for n in names), *(rb[n] for n in names), str(self.objective.pv), *obs]

    def safety_lines(self) -> list[str]:
        """The safety limits of the run, one line each (printed when a run is resumed from the
        log header alone)."""
        floor = "none" if self.objective_floor is None else f"{self.objective_floor:g}"
        box = ", ".join(f"{n} [{lo:g}, {hi:g}]" for n, (lo, hi) in self.knobs.items())
        return [
            f"knobs and bounds: {box}",
            f"max_step: {self.max_step}",
            f"restore: {self.restore}; objective floor: {floor}; read retries: "
            f"{self.read_retries}; readback tolerance: {self.readback_tolerance:g} of the range",
            f"restore window: {self.restore_timeout:g} s ({self.restore_attempts} attempt(s) "
            f"at least, {self.restore_interval:g} s apart)",
        ]

    def get_prior(self):
        """The loaded :class:`~pigp_torch.prior.PhysicsPrior` (``None`` without a prior file, or
        before :func:`pigp_torch.loop.run.validate_config` loaded it)."""
        return self._prior

    def attach_prior(self, prior) -> None:
        """Keep ``prior``, the :class:`~pigp_torch.prior.PhysicsPrior` read from :attr:`prior`
        (the run layer reads and checks the file; this module does no I/O)."""
        self._prior = prior


def logged_units(header: dict) -> tuple[str, str]:
    """``(objective_unit, knob_unit)`` of a run log's header (its configuration's); a log written
    before run files named their units gets the defaults, ``("mA/min", "A")``."""
    config = header.get("config") or {}
    fields = RunConfig.model_fields
    return (
        str(config.get("objective_unit") or fields["objective_unit"].default),
        str(config.get("knob_unit") or fields["knob_unit"].default),
    )


def config_digest(dump: dict) -> str:
    """Hex sha256 of a configuration dump (``model_dump(mode="json")``), canonical JSON."""
    text = json.dumps(dump, sort_keys=True, separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()
