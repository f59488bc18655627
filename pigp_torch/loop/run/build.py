r"""Building a run from a validated configuration: the optimizer (from the method registry), the
machine (simulated or EPICS), the prior's provenance, and the loop with the run's safety options.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pigp_torch.data.runlog import file_sha256
from pigp_torch.loop.config import (
    ConfigError,
    EpicsMachineConfig,
    RunConfig,
    config_digest,
)
from pigp_torch.machines import KINDS, MachineKind
from pigp_torch.methods import METHODS, RunContext


def machine_kind(config: RunConfig) -> MachineKind | None:
    """The machine kind whose run-file section ``config.machine`` is (``kind: sim`` the ring's,
    ``kind: ares-sim`` ARES-EA's); ``None`` for ``kind: epics``, the loop's own (a live
    machine)."""
    return KINDS.by_run_file_kind(config.machine.kind)


def build_optimizer(config: RunConfig, machine=None):
    r"""The configured optimizer (nothing is connected; bad option values raise here).

    The registry's builder of ``config.method.name`` with the run's options, bounds, seed and
    direction, and no archive (a live machine has none). On a machine kind's section (``kind:
    sim``, ``kind: ares-sim``) the builder is given the kind's simulated machine (``machine``, or
    one built from ``config``: a simulation, nothing to connect), whose target the kind's methods
    read, and the reading noise the kind tells its methods
    (:meth:`~pigp_torch.machines.MachineKind.methods_noise`); otherwise no noise level (each
    optimizer keeps its own default, or ``noise`` from the options).

    Raises:
        ConfigError: the builder refused an option value.
    """
    name = config.method.name
    spec = METHODS[name].with_options(**config.method.options)
    noise = None
    kind = machine_kind(config)
    if kind is not None:
        machine = kind.simulated_machine(config) if machine is None else machine
        noise = kind.methods_noise(config.machine)
    ctx = RunContext(
        machine=machine,
        prior=config.get_prior(),
        seed=config.method.seed,
        noise=noise,
        archive_size=0,
        maximize=config.objective.maximize,
        knob_bounds=config.bounds(),
    )
    try:
        return spec.build(ctx)
    except (TypeError, ValueError) as err:
        raise ConfigError(f"method {name}: {err}") from err


def build_machine(config: RunConfig):
    r"""Construct the configured machine: a machine kind's simulated machine
    (:meth:`~pigp_torch.machines.MachineKind.simulated_machine`), or connect the EPICS machine.
    Nothing is moved."""
    kind = machine_kind(config)
    if kind is not None:
        return kind.simulated_machine(config)
    names, bounds, m = config.knob_names, config.bounds(), config.machine
    tolerance = m.tolerance
    if m.tolerance_fraction is not None:
        tolerance = m.tolerance_fraction * (bounds[1] - bounds[0])
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
        observable_pvs=m.observable_pvs,
        observable_units=m.observable_units,
        refuse_severity=m.refuse_severity,
    )


def prior_record(config: RunConfig) -> dict | None:
    """The prior's provenance for the run log: path, sha256 of the file, its metadata."""
    prior = config.get_prior()
    if prior is None:
        return None
    return {
        "path": str(Path(config.prior).resolve()),
        "sha256": file_sha256(config.prior),
        "knob_names": list(prior.knob_names),
        "metadata": prior.provenance,
    }


def machine_header(machine) -> dict:
    """Run-log header entries a machine describes itself with: ``knob_units`` (one per knob),
    ``observable_names`` and ``observable_units`` (what each reading also measures); only those
    the machine has."""
    out = {}
    for key in ("knob_units", "observable_names", "observable_units"):
        value = getattr(machine, key)  # declared by the Machine protocol (default None)
        if value is not None:
            out[key] = [str(v) for v in value]
    return out


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
        prior provenance, knobs, bounds; a machine's own knob units (``knob_units``) and the
        names and units of its observables (``observable_names``, ``observable_units``) where
        it has them."""
        dump = self.config.model_dump(mode="json")
        header = {
            "knob_names": self.config.knob_names,
            "method": self.method,
            "bounds": self.config.bounds().tolist(),
            "maximize": self.config.objective.maximize,
            "config": dump,
            "config_sha256": config_digest(dump),
            "prior": self.prior_info,
        }
        return header | machine_header(self.machine)

    def run(self, *, log=None, resume=None, progress: bool = False, callback=None):
        r"""Run the loop with the configured safety options (ramped moves, read retries, floor,
        restore, readback check); returns the evaluation table (see :func:`pigp_torch.optimize`;
        ``mode: track``: :func:`pigp_torch.loop.track`).
        """
        from pigp_torch.loop import optimize, track

        c = self.config
        if c.mode == "track":  # until stopped, the time limit or budget readings
            return track(self.machine, self.optimizer, c.budget, time_limit_s=c.time_limit_s(),
                         end_at=c.restore, recent=c.best_window, method=self.method,
                         progress=progress, callback=callback, log=log, resume=resume,
                         options=self.options())  # fmt: skip
        return optimize(
            self.machine,
            self.optimizer,
            None,
            self.config.budget,
            method=self.method,
            progress=progress,
            callback=callback,
            log=log,
            resume=resume,
            options=self.options(),
        )

    def options(self):
        r"""The loop's safety options of this run (:class:`~pigp_torch.loop.RunOptions`): every
        proposal ramped to, the configured restore, read retries, floor and readback check. The
        step limit is the machine's own (:func:`build_machine` gives it ``max_step``; the loop
        reads it from there), so it is not repeated here."""
        from pigp_torch.loop import RunOptions

        c = self.config
        restore = {"current": "none"}.get(c.restore, c.restore)
        return RunOptions(
            restore="initial" if c.mode == "track" else restore,  # a track run: its own end
            read_retries=c.read_retries,
            retry_interval=c.retry_interval,
            objective_floor=c.objective_floor,
            readback_tol=c.readback_tolerance,
            restore_attempts=c.restore_attempts,
            restore_interval=c.restore_interval,
            restore_timeout=c.restore_timeout,
            noise=self.stated_noise(),
            objective_range=c.objective_range,
            noise_reads=c.noise_reads if self.measures_noise() else 0,
        )

    def measures_noise(self) -> bool:
        """Whether the run measures its noise at the start: ``kind: epics`` stating none."""
        return isinstance(self.config.machine, EpicsMachineConfig) and self.stated_noise() is None

    def stated_noise(self) -> float | None:
        """The noise of one reading the run states: ``objective_noise``, else the noise the
        machine kind states of its simulated machine
        (:meth:`~pigp_torch.machines.MachineKind.stated_noise`), else the prior's (``None``: none
        stated)."""
        c = self.config
        if c.objective_noise is not None:
            return c.objective_noise
        kind = machine_kind(c)
        noise = kind.stated_noise(c.machine) if kind is not None else None
        if noise is not None:
            return noise
        prior = c.get_prior()
        noise = prior.noise if prior is not None else None
        return float(noise) if noise else None


def build_run(config: RunConfig) -> RunSetup:
    r"""Build a run from a validated configuration: the prior's provenance, then the optimizer
    and the machine. A machine kind's simulated machine (``kind: sim``, ``kind: ares-sim``: a
    simulation, nothing is connected or moved) is built first, as the kind's methods read it; an
    EPICS machine last, once the optimizer is built (bad option values raise
    :class:`ConfigError` before anything connects).
    """
    info = prior_record(config)
    if machine_kind(config) is not None:
        machine = build_machine(config)
        return RunSetup(config, build_optimizer(config, machine), machine, info)
    optimizer = build_optimizer(config)
    machine = build_machine(config)
    return RunSetup(config=config, optimizer=optimizer, machine=machine, prior_info=info)
