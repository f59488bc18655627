r"""Run configuration of ``pigp optimize``: validated models, loading, and building the run.

A run file (YAML or JSON) names everything a run on a machine needs; it is validated as a whole
(pydantic v2, unknown keys refused) before anything is connected or moved::

    machine:                      # sim: the simulated SPEAR3 ring; epics: Channel Access
      kind: sim
      error_seed: 1
      noise: 0.04                 # mA/min
    knobs:                        # name: [lower, upper], in knob units (amperes of the windings)
      01G-QSS4: [-30, 30]
      02G-QSS3: [-30, 30]
    objective: {maximize: true}   # epics: {pv: SPEAR:BeamLossRate, maximize: true}
    method: {name: nelder-mead, options: {initial_simplex_size: 0.05}}
    prior: prior.json             # a PhysicsPrior file (needed by pigp), knobs must match
    budget: 60
    max_step: 0.1                 # required: fraction of each knob's half-range, {knob: value},
                                  # or the word unlimited (no step limit, deliberately)
    log: runs/sim.jsonl           # the run log (JSON lines)
    restore: initial              # or best (set the best observed point at the end)
    read_retries: 2
    objective_floor: null         # abort when a reading falls below this

Relative paths (``prior``, ``log``, ``lock_dir``) are taken relative to the run file's folder.

A key given twice in a file is an error (YAML and JSON alike), not "the last one wins".
``max_step`` has no default: a number, a per-knob mapping, or the word ``unlimited``; ``null``
is refused. :meth:`RunConfig.warnings` names every step limit above 10 % of its knob's range
(``pigp optimize`` prints them).

Methods (``method.name``; ``method.options`` are checked against the builder's arguments):

* ``pigp``: physics-informed BayesOpt, as :func:`pigp_torch.benchmark.methods.build_pigp`: kernel
  (``kernel``: rbf/rq), mean (``mean``: f_inf/zero/float) and noise from the prior; BayesOpt
  options over :data:`pigp_torch.benchmark.methods.BO_DEFAULTS` (UCB, beta 4, trust box 0.3).
* ``pigp-fast``: the same method as ``pigp`` (RBF kernel; ``mean`` f_inf/zero/float) on
  :class:`~pigp_torch.optimizers.fast_bo.FastBayesOpt`, 12-18x faster per step (less dead beam
  time between readings); its options (``acquisition``, ``beta``, ``step_limit``,
  ``trust_center``, ``num_restarts``, ``raw_samples``, ``n_previous``, ``method``, ``options``).
* ``pigp-physics``: :class:`~pigp_torch.optimizers.physics_bo.PhysicsModelBO` (the physics form of
  the loss rate fitted online, shape from the prior; options ``beta``, ``step_limit``,
  ``n_starts``, ``exploit_every``, the adaptive trust box ``adapt_box``, ``min_step_limit``,
  ``success_streak``, ``failure_streak``, ``success_tol``, ``center_prior``, ``shape_prior``,
  and the model's ``center_std``, ``center_cov_scale``, ``center_floor_std``, ``log_c_std``,
  ``log_beta_std``, ``residual_std``, ``f_inf_std``, ``shape_std``, ``noise``); needs a prior
  file, best one built with ``pigp build-prior --center-ensemble 40`` (the prior on where the
  optimum lies and the mean shape of the peak).
* ``ml2``: BayesOpt with the ML-II diagonal GP, with no archive (a live machine has none at hand):
  hyperparameters fitted on the run data every ``refit_every`` asks (warm-started); ``noise``
  fixes the noise (``None``: learned).
* ``nelder-mead``: :class:`~pigp_torch.optimizers.NelderMead` options;
* ``rcds``: :class:`~pigp_torch.optimizers.RCDS` options (``noise``, ``step``, ``directions``).

Every error is reported at once, one line per problem, as a :class:`ConfigError` (a
``ValueError``) naming the key: a wrong key, a missing PV name, bounds with lower >= upper, a
prior whose knobs differ from the run's, unknown method options.
"""

from __future__ import annotations

import difflib
import inspect
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

import torch
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    PrivateAttr,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)

from pigp_torch._utils import DTYPE

METHOD_NAMES = ("pigp", "pigp-fast", "pigp-physics", "ml2", "nelder-mead", "rcds")
#: Methods built from the physics prior (they need ``prior`` and ``objective.maximize``).
PRIOR_METHODS = ("pigp", "pigp-fast", "pigp-physics")


class ConfigError(ValueError):
    """An invalid run configuration (the message lists every problem, one per line)."""


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


# ------------------------------------------------------------------------------------ models
class SimMachineConfig(_Section):
    r"""The simulated ring: :class:`~pigp_torch.simulation.Spear3Coupling` behind a
    :class:`~pigp_torch.machine.SimulatedMachine` with Gaussian reading noise.

    The configured knobs are the simulator's skew windings (names like ``01G-QSS4``); their bounds
    must lie within the simulator's range (±30 A).

    Attributes:
        error_seed: error seed of the simulated machine.
        optics: the SPEAR3 deck, ``"user"`` (default), ``"design"`` or ``"low_emittance"``.
        noise: reading noise standard deviation (mA/min).
        seed: seed of the noise stream.
        x_init: knob values the machine starts at (unlisted knobs: 0).
    """

    kind: Literal["sim"]
    error_seed: int = 1
    optics: Literal["user", "design", "low_emittance"] = "user"
    noise: float = Field(0.04, ge=0.0)
    seed: int = 0
    x_init: dict[str, float] | None = None


class EpicsMachineConfig(_Section):
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
    configured from ``EPICS_PVA_*`` in the environment).
    """

    kind: Literal["epics"]
    protocol: Literal["ca", "pva"] = "ca"
    setpoint_pvs: dict[str, str] | None = None
    readback_pvs: dict[str, str] | None = None
    setpoint_suffix: str = ":CurrSetpt"
    readback_suffix: str = ":Curr1"
    settle_time: float = Field(0.5, ge=0.0)
    tolerance: float | None = Field(None, gt=0.0)
    tolerance_fraction: float | None = Field(None, gt=0.0, lt=1.0)
    n_average: int = Field(1, ge=1)
    average_interval: float = Field(0.0, ge=0.0)
    timeout: float = Field(2.0, gt=0.0)
    stale_timeout: float = Field(10.0, gt=0.0)

    @model_validator(mode="after")
    def _one_tolerance(self) -> EpicsMachineConfig:
        if self.tolerance is not None and self.tolerance_fraction is not None:
            raise ValueError("give tolerance (knob units) or tolerance_fraction, not both")
        return self


MachineConfig = Annotated[SimMachineConfig | EpicsMachineConfig, Field(discriminator="kind")]


class ObjectiveConfig(_Section):
    """What is optimized: ``pv`` (EPICS only) and the direction."""

    pv: str | None = None
    maximize: bool = True


class MethodConfig(_Section):
    """The optimizer: ``name`` (one of :data:`METHOD_NAMES`), its ``options`` and its ``seed``
    (BayesOpt's per-ask seed; Nelder–Mead and RCDS are deterministic)."""

    name: Literal["pigp", "pigp-fast", "pigp-physics", "ml2", "nelder-mead", "rcds"]
    seed: int = 0
    options: dict[str, Any] = Field(default_factory=dict)


def _resolve(path: Path | None, info: ValidationInfo) -> Path | None:
    base = (info.context or {}).get("base_dir")
    if path is None or path.is_absolute() or base is None:
        return path
    return Path(os.path.normpath(Path(base) / path))  # "a/../b" -> "b" (plain text, no I/O)


class RunConfig(_Section):
    r"""A validated ``pigp optimize`` run (see the module docstring for the file format).

    Attributes:
        machine: :class:`SimMachineConfig` or :class:`EpicsMachineConfig` (by ``kind``).
        knobs: ``{name: (lower, upper)}`` in knob order.
        objective: :class:`ObjectiveConfig`.
        method: :class:`MethodConfig`.
        prior: a :class:`~pigp_torch.prior.PhysicsPrior` JSON file (required by ``pigp``).
        budget: evaluations, the start point included.
        max_step: largest change of a knob per ``set`` (required): a fraction of each knob's
            half-range, ``{knob: absolute}``, or ``"unlimited"`` (no step limit).
        log: the run log to write.
        restore: ``"initial"`` (put the knobs back) or ``"best"`` (set the best observed point).
        read_retries: extra read attempts after an invalid reading (the loop's; the EPICS
            machine is given none of its own, so this is the total).
        retry_interval: seconds before each extra read attempt.
        objective_floor: abort when a reading falls below this (``None``: no floor).
        readback_tolerance: allowed readback error after the final set, a fraction of the range.
        restore_attempts: attempts at restoring the knobs at the end (default 3).
        restore_interval: seconds between those attempts (default 1).
        lock_dir: folder of the machine locks (default ``$PIGP_LOCK_DIR`` or
            ``<tmp>/pigp-locks``; see :mod:`pigp_torch.runlock`).
    """

    machine: MachineConfig
    knobs: dict[str, tuple[float, float]]
    objective: ObjectiveConfig = Field(default_factory=ObjectiveConfig)
    method: MethodConfig
    prior: Path | None = None
    budget: int = Field(ge=1)
    max_step: float | dict[str, float] | Literal["unlimited"]
    log: Path
    restore: Literal["initial", "best"] = "initial"
    read_retries: int = Field(2, ge=0)
    retry_interval: float = Field(0.1, ge=0.0)
    objective_floor: float | None = None
    readback_tolerance: float = Field(1e-3, ge=0.0)
    restore_attempts: int = Field(3, ge=1, le=100)
    restore_interval: float = Field(1.0, ge=0.0)
    lock_dir: Path | None = None

    _prior = PrivateAttr(default=None)

    @field_validator("max_step", mode="before")
    @classmethod
    def _explicit_max_step(cls, value):
        if value is None:
            raise ValueError(
                "null is not a step limit: give a fraction of each knob's half-range (e.g. 0.1), "
                "a {knob: value} mapping, or write unlimited to run without a step limit"
            )
        if isinstance(value, str) and value != "unlimited":
            raise ValueError(
                f"{value!r} is not a step limit: give a number, a {{knob: value}} mapping, or "
                "the word unlimited (no step limit)"
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
        return _resolve(path, info)

    @model_validator(mode="after")
    def _check_run(self) -> RunConfig:
        names = list(self.knobs)
        if isinstance(self.max_step, dict):
            _same_knobs("max_step", self.max_step, names)
            bad = [k for k, v in self.max_step.items() if not v > 0]
            if bad:
                raise ValueError(f"max_step: the limits of {bad} must be positive")
        elif isinstance(self.max_step, float) and not self.max_step > 0:
            raise ValueError(f"max_step must be positive (or unlimited), got {self.max_step}")
        m = self.machine
        if isinstance(m, SimMachineConfig):
            if self.objective.pv is not None:
                raise ValueError("objective.pv is for the epics machine; the sim reads its model")
            for name, value in (m.x_init or {}).items():
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
        _check_method(self.method, self.objective)
        if self.method.name in PRIOR_METHODS and self.prior is None:
            raise ValueError(
                f"prior: method {self.method.name} needs a prior file (pigp build-prior)"
            )
        if self.prior is not None:
            self._prior = _load_prior(self.prior, names)
        return self

    # -- derived values ---------------------------------------------------------------------------
    @property
    def knob_names(self) -> list[str]:
        return list(self.knobs)

    def bounds(self) -> torch.Tensor:
        """``2 x d`` knob bounds in knob order."""
        return torch.tensor(list(zip(*self.knobs.values(), strict=True)), dtype=DTYPE)

    def machine_max_step(self) -> float | torch.Tensor | None:
        """``max_step`` as the machines take it: a fraction, a ``d`` absolute tensor, or
        ``None`` (unlimited)."""
        if isinstance(self.max_step, dict):
            return torch.tensor([self.max_step[n] for n in self.knobs], dtype=DTYPE)
        if self.max_step == "unlimited":
            return None
        return self.max_step

    def warnings(self) -> list[str]:
        """Safety warnings (no error): no step limit, or a knob's limit above 10 % of its
        range (one line naming every such knob)."""
        if self.max_step == "unlimited":
            return ["max_step: unlimited: no step limit, a proposal is reached in one set"]
        from pigp_torch.machine.base import max_step_tensor

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
        """Every PV the run uses (setpoints, readbacks, objective); empty for the simulator."""
        m = self.machine
        if not isinstance(m, EpicsMachineConfig):
            return []
        names = self.knob_names
        sp = m.setpoint_pvs or {n: f"{n}{m.setpoint_suffix}" for n in names}
        rb = m.readback_pvs or {n: f"{n}{m.readback_suffix}" for n in names}
        return [*(sp[n] for n in names), *(rb[n] for n in names), str(self.objective.pv)]

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
        ]

    def get_prior(self):
        """The loaded :class:`~pigp_torch.prior.PhysicsPrior` (``None`` without a prior file)."""
        return self._prior


def _same_knobs(key: str, mapping: dict, names: list[str], what: str = "missing knobs") -> None:
    missing = [n for n in names if n not in mapping]
    extra = [k for k in mapping if k not in names]
    if missing:
        raise ValueError(f"{key}: {what} {missing}")
    if extra:
        raise ValueError(f"{key}: {extra} are not configured knobs")


def method_options(name: str) -> set[str]:
    """Option names accepted by method ``name`` (from the builders' signatures)."""
    from pigp_torch.optimizers import RCDS, BayesOpt, NelderMead

    def params(cls, *skip: str) -> set[str]:
        sig = inspect.signature(cls.__init__).parameters
        return set(sig) - {"self", "bounds", "maximize", *skip}

    if name == "pigp":
        return params(BayesOpt, "model", "seed") | {"kernel", "mean"}
    if name == "ml2":
        return params(BayesOpt, "model", "seed") | {"refit_every", "noise"}
    if name == "pigp-fast":
        from pigp_torch.optimizers.fast_bo import FastBayesOpt

        return params(FastBayesOpt, "precision", "amplitude", "noise", "seed") | {"mean"}
    if name == "pigp-physics":
        from pigp_torch.optimizers.physics_bo import PhysicsModelBO

        model = {"center_std", "log_c_std", "log_beta_std", "residual_std", "f_inf_std"}
        model |= {"center_cov_scale", "center_floor_std", "shape_std"}
        model |= {"noise", "max_iter"}
        return params(PhysicsModelBO, "prior", "seed", "model_options") | model
    if name == "nelder-mead":
        return params(NelderMead)
    if name == "rcds":
        return params(RCDS)
    raise ValueError(f"unknown method {name!r}; known: {METHOD_NAMES}")


def _check_method(method: MethodConfig, objective: ObjectiveConfig) -> None:
    allowed = method_options(method.name)
    unknown = sorted(set(method.options) - allowed)
    if unknown:
        raise ValueError(
            f"method.options: unknown option(s) {unknown} for {method.name} "
            f"(allowed: {', '.join(sorted(allowed))})"
        )
    if method.name in PRIOR_METHODS and not objective.maximize:
        raise ValueError(
            f"method {method.name} needs objective.maximize: true "
            "(the physics prior describes a peak)"
        )


def _load_prior(path: Path, names: list[str]):
    from pigp_torch.prior import PhysicsPrior

    if not path.is_file():
        raise ValueError(f"prior: no such file {str(path)!r}")
    try:
        prior = PhysicsPrior.load(path)
    except ValueError as err:
        raise ValueError(f"prior: {path} is not a valid PhysicsPrior file: {err}") from err
    if prior.knob_names != names:
        raise ValueError(
            f"prior: the knobs of {path.name} {prior.knob_names} do not match the configured "
            f"knobs {names} (same names in the same order are needed)"
        )
    return prior


# ------------------------------------------------------------------------------------ loading
_SECTIONS = {
    (): RunConfig,
    ("objective",): ObjectiveConfig,
    ("method",): MethodConfig,
}


def _allowed_keys(parent: tuple[str, ...], data: Any) -> list[str]:
    model = _SECTIONS.get(parent)
    if parent == ("machine",):
        kind = data.get("machine", {}).get("kind") if isinstance(data, dict) else None
        model = {"sim": SimMachineConfig, "epics": EpicsMachineConfig}.get(kind)
    return list(model.model_fields) if model is not None else []


def _format_errors(err: ValidationError, data: Any) -> list[str]:
    lines = []
    for e in err.errors():
        loc = [str(p) for p in e["loc"]]
        if len(loc) >= 2 and loc[0] == "machine" and loc[1] in ("sim", "epics"):
            del loc[1]  # the union tag pydantic adds
        where = ".".join(loc)
        msg = e["msg"].removeprefix("Value error, ")
        if e["type"] == "extra_forbidden":
            allowed = _allowed_keys(tuple(loc[:-1]), data)
            line = f"unknown key {where!r}"
            close = difflib.get_close_matches(loc[-1], allowed, n=1)
            if close:
                line += f" (did you mean {close[0]!r}?)"
            if allowed:
                line += f"; allowed: {', '.join(allowed)}"
        elif e["type"] == "missing":
            line = f"missing key {where!r}"
            if where == "max_step":
                line += (
                    " (a fraction of each knob's half-range, a {knob: value} mapping, or "
                    "unlimited: the step limit must be given explicitly)"
                )
        else:
            line = f"{where}: {msg}" if where else msg
        lines.append(line)
    return lines


def validate_config(data: Any, *, base_dir: str | Path | None = None, source: str = "config"):
    r"""Validate a configuration mapping; returns a :class:`RunConfig`.

    Args:
        data: the parsed file (a mapping).
        base_dir: folder that relative paths are taken from (``None``: as given).
        source: name used in error messages (the file name).

    Raises:
        ConfigError: every problem found, one per line.
    """
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: a run configuration must be a mapping of keys to values")
    context = {"base_dir": None if base_dir is None else Path(base_dir)}
    try:
        return RunConfig.model_validate(data, context=context)
    except ValidationError as err:
        lines = _format_errors(err, data)
        raise ConfigError(
            f"{source}: invalid run configuration: " + lines[0]
            if len(lines) == 1
            else f"{source}: invalid run configuration:\n  - " + "\n  - ".join(lines)
        ) from None


def _no_duplicates_json(pairs):
    out = {}
    for key, value in pairs:
        if key in out:
            raise ConfigError(f"duplicate key {key!r}; a key may appear only once")
        out[key] = value
    return out


def _unique_key_loader():
    """A ``yaml.SafeLoader`` subclass that refuses a mapping key given twice."""
    import yaml

    class UniqueKeyLoader(yaml.SafeLoader):
        pass

    def construct_mapping(loader, node, deep=False):
        loader.flatten_mapping(node)
        seen = {}
        for key_node, _ in node.value:
            key = loader.construct_object(key_node, deep=deep)
            if key in seen:
                raise ConfigError(
                    f"duplicate key {key!r} (line {key_node.start_mark.line + 1}, first given on "
                    f"line {seen[key] + 1}); a key may appear only once"
                )
            seen[key] = key_node.start_mark.line
        return yaml.SafeLoader.construct_mapping(loader, node, deep=deep)

    UniqueKeyLoader.add_constructor(
        yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, construct_mapping
    )
    return UniqueKeyLoader


def load_config(path: str | Path) -> RunConfig:
    r"""Read a run file (``.json``: JSON, anything else: YAML, safe loader) and validate it.

    Relative ``prior``, ``log`` and ``lock_dir`` paths are taken relative to the file's folder.

    Raises:
        FileNotFoundError: no such file.
        ConfigError: unreadable or invalid configuration (every problem, one per line), or a key
            given twice.
    """
    path = Path(path)
    text = path.read_text(encoding="utf-8")
    if path.suffix.lower() == ".json":
        try:
            data = json.loads(text, object_pairs_hook=_no_duplicates_json)
        except json.JSONDecodeError as err:
            raise ConfigError(f"{path}: not valid JSON: {err}") from err
        except ConfigError as err:
            raise ConfigError(f"{path}: {err}") from None
    else:
        import yaml

        try:
            data = yaml.load(text, Loader=_unique_key_loader())  # a SafeLoader subclass
        except ConfigError as err:
            raise ConfigError(f"{path}: {err}") from None
        except yaml.YAMLError as err:
            raise ConfigError(f"{path}: not valid YAML: {err}") from err
    return validate_config(data, base_dir=path.parent.absolute(), source=str(path))


# ------------------------------------------------------------------------------------ building
class _BoundedSim:
    """A simulator seen with the run's knob bounds (the simulated machine takes them from it)."""

    def __init__(self, sim, bounds: torch.Tensor) -> None:
        self.sim = sim
        self.bounds = bounds
        self.knob_names = list(sim.knob_names)

    def evaluate(self, x):
        return self.sim.evaluate(x)

    def __repr__(self) -> str:
        return f"{self.sim!r} within the run's bounds"


def build_optimizer(config: RunConfig):
    r"""The configured optimizer (nothing is connected; bad option values raise here)."""
    from pigp_torch.optimizers import RCDS, BayesOpt, NelderMead

    bounds = config.bounds()
    opts = dict(config.method.options)
    name, maximize, seed = config.method.name, config.objective.maximize, config.method.seed
    try:
        if name in ("pigp", "ml2"):
            from pigp_torch.benchmark.methods import BO_DEFAULTS  # one source of the defaults

            factory = _pigp_factory(config, opts) if name == "pigp" else _ml2_factory(bounds, opts)
            return BayesOpt(
                bounds, factory, maximize=maximize, seed=seed, **{**BO_DEFAULTS, **opts}
            )
        if name == "pigp-fast":
            from pigp_torch.benchmark.methods import fast_bo_options
            from pigp_torch.optimizers.fast_bo import FastBayesOpt

            return FastBayesOpt.from_prior(
                bounds, config.get_prior(), maximize=maximize, seed=seed, **fast_bo_options(opts)
            )
        if name == "pigp-physics":
            from pigp_torch.optimizers.physics_bo import PhysicsModelBO

            return PhysicsModelBO(bounds, config.get_prior(), seed=seed, **opts)
        if name == "nelder-mead":
            return NelderMead(bounds, maximize=maximize, **opts)
        return RCDS(bounds, maximize=maximize, **opts)
    except (TypeError, ValueError) as err:
        raise ConfigError(f"method {name}: {err}") from err


def _pigp_factory(config: RunConfig, opts: dict):
    from pigp_torch.models import physics_informed_gp

    prior = config.get_prior()
    kernel, mean = opts.pop("kernel", "rbf"), opts.pop("mean", "f_inf")

    def factory(X, Y):
        return physics_informed_gp(X, Y, prior, kernel=kernel, mean=mean)

    factory(prior.x0[None], torch.tensor([[prior.f_x0]], dtype=DTYPE))  # bad kernel/mean: now
    return factory


def _ml2_factory(bounds: torch.Tensor, opts: dict):
    r"""ML-II GP without an archive: hyperparameters fitted on the run data every
    ``refit_every`` asks (warm-started from the previous fit), frozen in between."""
    from pigp_torch.models import ml2_gp

    refit_every, noise = int(opts.pop("refit_every", 1)), opts.pop("noise", None)
    if refit_every < 1:
        raise ValueError(f"refit_every must be >= 1 (no archive to fit once), got {refit_every}")
    state: dict[str, Any] = {"hyper": None, "calls": 0}

    def factory(X, Y):
        refit = state["hyper"] is None or state["calls"] % refit_every == 0
        model = ml2_gp(X, Y, bounds=bounds, refit=refit, noise=noise, state_dict=state["hyper"])
        state["calls"] += 1
        if refit:
            state["hyper"] = {k: v.detach().clone() for k, v in model.state_dict().items()}
        return model

    return factory


def build_machine(config: RunConfig):
    r"""Construct (and, for EPICS, connect) the configured machine. Nothing is moved."""
    names, bounds, m = config.knob_names, config.bounds(), config.machine
    tolerance = m.tolerance if isinstance(m, EpicsMachineConfig) else None
    if isinstance(m, EpicsMachineConfig) and m.tolerance_fraction is not None:
        tolerance = m.tolerance_fraction * (bounds[1] - bounds[0])
    if isinstance(m, SimMachineConfig):
        from pigp_torch.machine import SimulatedMachine
        from pigp_torch.simulation import Spear3Coupling

        sim = Spear3Coupling(m.error_seed, knobs=names, optics=m.optics)
        outside = [
            n
            for n, lo, hi in zip(names, bounds[0].tolist(), bounds[1].tolist(), strict=True)
            if lo < float(sim.bounds[0, 0]) or hi > float(sim.bounds[1, 0])
        ]
        if outside:
            raise ConfigError(
                f"knobs {outside}: bounds outside the simulator's range "
                f"[{float(sim.bounds[0, 0])}, {float(sim.bounds[1, 0])}]"
            )
        x_init = torch.tensor([(m.x_init or {}).get(n, 0.0) for n in names], dtype=DTYPE)
        x_init = torch.minimum(torch.maximum(x_init, bounds[0]), bounds[1])  # 0 may lie outside
        return SimulatedMachine(
            _BoundedSim(sim, bounds),
            noise=m.noise,
            seed=m.seed,
            max_step=config.machine_max_step(),
            x_init=x_init,
        )
    if m.protocol == "pva":
        from pigp_torch.machine.pva import PvaMachine as EpicsMachine  # lazily: needs p4p
    else:
        from pigp_torch.machine.epics import EpicsMachine  # lazily: needs caproto

    def pv_list(pvs: dict[str, str] | None) -> list[str] | None:
        return None if pvs is None else [pvs[n] for n in names]

    return EpicsMachine(
        names,
        bounds,
        config.objective.pv,
        setpoint_pvs=pv_list(m.setpoint_pvs),
        readback_pvs=pv_list(m.readback_pvs),
        setpoint_suffix=m.setpoint_suffix,
        readback_suffix=m.readback_suffix,
        settle_time=m.settle_time,
        tolerance=tolerance,
        n_average=m.n_average,
        average_interval=m.average_interval,
        timeout=m.timeout,
        stale_timeout=m.stale_timeout,
        max_step=config.machine_max_step(),
        read_retries=0,  # the loop retries (config.read_retries), for every machine alike
    )


def prior_record(config: RunConfig) -> dict | None:
    """The prior's provenance for the run log: path, sha256 of the file, its metadata."""
    from pigp_torch.runlog import file_sha256

    prior = config.get_prior()
    if prior is None:
        return None
    return {
        "path": str(Path(config.prior).resolve()),
        "sha256": file_sha256(config.prior),
        "knob_names": list(prior.knob_names),
        "metadata": prior.provenance,
    }


@dataclass
class RunSetup:
    r"""Everything built for one run: the configuration, optimizer, machine and prior provenance.

    Attributes:
        config: the validated configuration.
        optimizer: a fresh ask/tell optimizer.
        machine: the machine (constructed last).
        prior_info: :func:`prior_record` of the prior (``None`` without one).
    """

    config: RunConfig
    optimizer: Any
    machine: Any
    prior_info: dict | None = None

    @property
    def method(self) -> str:
        return self.config.method.name

    def header(self) -> dict:
        """Header entries of the run log: configuration (and its :func:`config_digest`),
        prior provenance, knobs, bounds."""
        dump = self.config.model_dump(mode="json")
        return {
            "knob_names": self.config.knob_names,
            "method": self.method,
            "bounds": self.config.bounds().tolist(),
            "maximize": self.config.objective.maximize,
            "config": dump,
            "config_sha256": config_digest(dump),
            "prior": self.prior_info,
        }

    def run(self, *, log=None, resume=None, progress: bool = False, callback=None):
        r"""Run the loop with the configured safety options (ramped moves, read retries, floor,
        restore, readback check); returns the evaluation table (see :func:`pigp_torch.optimize`).
        """
        from pigp_torch.loop import optimize

        c = self.config
        return optimize(
            self.machine,
            self.optimizer,
            None,
            c.budget,
            method=self.method,
            progress=progress,
            callback=callback,
            restore=c.restore,
            moves="ramp",
            max_step=c.machine_max_step(),
            read_retries=c.read_retries,
            retry_interval=c.retry_interval,
            objective_floor=c.objective_floor,
            log=log,
            resume=resume,
            readback_tol=c.readback_tolerance,
            restore_attempts=c.restore_attempts,
            restore_interval=c.restore_interval,
        )


def build_run(config: RunConfig) -> RunSetup:
    r"""Build a run from a validated configuration: the prior's provenance, then the optimizer
    (bad option values raise :class:`ConfigError` here), then — last — the machine.
    """
    info = prior_record(config)
    optimizer = build_optimizer(config)
    machine = build_machine(config)
    return RunSetup(config=config, optimizer=optimizer, machine=machine, prior_info=info)


# ------------------------------------------------------------------------------------ resume
def check_resume(config: RunConfig, records) -> None:
    r"""Check that a run log comes from this configuration, so that it can be continued.

    The logged configuration must equal ``config`` except ``budget`` (which may grow) and
    ``log``; the prior file must still have the logged sha256.

    Raises:
        ConfigError: the configurations differ (the keys are named) or the prior changed.
    """
    from pigp_torch.runlog import file_sha256

    logged = dict(records.header.get("config") or {})
    if not logged:
        raise ConfigError(f"{records.path}: the log holds no configuration to continue")
    try:  # defaults of keys added since the log was written are filled in
        logged = validate_config(logged, source=str(records.path)).model_dump(mode="json")
    except ConfigError:
        pass  # compared as logged: the differences are named below
    now = config.model_dump(mode="json")
    keys = (set(now) | set(logged)) - {"budget", "log"}
    differ = sorted(k for k in keys if now.get(k) != logged.get(k))
    if differ:
        raise ConfigError(
            f"the configuration differs from the logged run in {differ}; a run can only be "
            "continued with its own configuration (the budget may change)"
        )
    logged_prior = records.header.get("prior")
    if logged_prior and config.prior is not None:
        sha = file_sha256(config.prior)
        if sha != logged_prior.get("sha256"):
            raise ConfigError(
                f"prior {config.prior} changed since the run started "
                f"(sha256 {sha[:12]}…, logged {str(logged_prior.get('sha256'))[:12]}…)"
            )


def config_digest(dump: dict) -> str:
    """Hex sha256 of a configuration dump (``model_dump(mode="json")``), canonical JSON."""
    import hashlib

    text = json.dumps(dump, sort_keys=True, separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def logged_config(records) -> RunConfig:
    r"""The configuration stored in a run log's header, verified and validated again.

    The header's ``config_sha256`` must be the :func:`config_digest` of its ``config`` (an
    edited header — a doubled step limit — is refused); then the configuration is validated
    as a run file would be (prior file included).

    Raises:
        ConfigError: no configuration, no digest (a log of an older version: give the run file
            with ``--config``), a digest that does not match, or an invalid configuration.
    """
    data = records.header.get("config")
    if not data:
        raise ConfigError(f"{records.path}: the log holds no configuration")
    logged = records.header.get("config_sha256")
    if not logged:
        raise ConfigError(
            f"{records.path}: the log header has no configuration digest (config_sha256); "
            "give the run file with --config to continue it"
        )
    if config_digest(data) != logged:
        raise ConfigError(
            f"{records.path}: the configuration in the log header does not match its sha256 "
            f"(the header was edited); give the run file with --config to continue it"
        )
    return validate_config(data, source=f"{records.path} (logged configuration)")


def advance_simulated_noise(machine, n_reads: int) -> None:
    r"""Put a fresh simulated machine's noise stream where the logged run left it.

    A :class:`~pigp_torch.machine.SimulatedMachine` draws one normal variate per reading from its
    seeded generator; taking ``n_reads`` readings (through the public :meth:`read`, the knobs
    unmoved) moves the stream on exactly as many draws, so a resumed simulated run sees the noise
    an uninterrupted one would have. Other machines are left alone.
    """
    from pigp_torch.machine import SimulatedMachine

    if isinstance(machine, SimulatedMachine) and machine.noise > 0:
        for _ in range(int(n_reads)):
            machine.read()
