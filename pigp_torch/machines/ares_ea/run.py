r"""A run on the simulated ARES-EA linac (``machine: {kind: ares-sim}``): the checks of its run
file against the simulation and the method registry (:func:`check_ares`) and its machine
(:func:`build_ares_machine`).

The objective the machine returns is the one the method reads
(:func:`~.methods.ares_objective_for`: ``ares-physics`` the mean absolute error
to the target, ``published-nm`` the beam distance, both in m and minimized; every other method
the published BO's reward, dimensionless and maximized). The run file's ``objective.maximize``
may be left out (it is then the objective's direction) or must agree with it; its
``objective_unit`` (default the objective's: ``m`` or ``1``) must be that unit, and ``knob_unit``
defaults to :data:`ARES_KNOB_UNIT` (the knobs carry two units).
"""

from __future__ import annotations

import torch

from pigp_torch._utils import DTYPE
from pigp_torch.loop.config import RunConfig
from pigp_torch.machines.ares_ea.section import AresSimConfig

#: The run's knob unit on ARES-EA when the run file names none (three quadrupoles' k1 and two
#: correctors' angles; the log header keeps each knob's own unit).
ARES_KNOB_UNIT = "1/m^2 or rad"
#: Unit of each ARES objective.
ARES_OBJECTIVE_UNITS = {"reward": "1", "distance": "m", "mae": "m"}


def ares_objective_name(config: RunConfig) -> str:
    """The machine objective of an ARES run: the one its method reads."""
    from pigp_torch.machines.ares_ea.methods import ares_objective_for

    return ares_objective_for(config.method.name)


def check_ares(config: RunConfig) -> None:
    r"""Check a run file's ARES parts; fill in the direction and the units it left out.

    A method built for ARES-EA runs only on ``kind: ares-sim``. On ``ares-sim``: the knobs are
    the five ARES knobs in order, with bounds inside the magnets' ranges; ``model_error`` is a
    known case; the trials file holds ``trial``; ``objective.maximize`` (if given) and
    ``objective_unit`` (if given) agree with the method's objective. Not given, they are set
    here, and so is ``knob_unit`` (:data:`ARES_KNOB_UNIT`).

    Raises:
        ValueError: the first problem found (its message names the key).
    """
    from pigp_torch.machines.ares_ea.cases import check_case
    from pigp_torch.machines.ares_ea.machine import ARES_OBJECTIVES
    from pigp_torch.machines.ares_ea.simulation import KNOB_NAMES, KNOB_UNITS, knob_bounds
    from pigp_torch.methods import METHODS

    m, spec = config.machine, METHODS[config.method.name]
    if spec.machine == "ares-ea" and not isinstance(m, AresSimConfig):
        raise ValueError(
            f"method.name: {config.method.name} is a method of the ARES-EA linac; it runs on "
            "machine kind: ares-sim"
        )
    if not isinstance(m, AresSimConfig):
        return
    if config.knob_names != list(KNOB_NAMES):
        raise ValueError(
            f"knobs: an ares-sim run has the five ARES knobs {list(KNOB_NAMES)} in this order, "
            f"got {config.knob_names}"
        )
    limits = knob_bounds()
    outside = [
        f"{n} [{lo:g}, {hi:g}] {u}"
        for n, u, lo, hi in zip(KNOB_NAMES, KNOB_UNITS, *limits.tolist(), strict=True)
        if config.knobs[n][0] < lo or config.knobs[n][1] > hi
    ]
    if outside:
        raise ValueError(f"knobs: bounds outside the magnets' ranges {', '.join(outside)}")
    try:
        check_case(m.model_error)
    except ValueError as err:
        raise ValueError(f"machine.model_error: {err}") from None
    _check_trial(m)
    objective = ares_objective_name(config)
    maximize = ARES_OBJECTIVES[objective]
    if "maximize" not in config.objective.model_fields_set:
        config.objective.maximize = maximize
    elif config.objective.maximize != maximize:
        raise ValueError(
            f"objective.maximize: {config.method.name} reads the ARES objective {objective!r}, "
            f"which is {'maximized' if maximize else 'minimized'}; write maximize: "
            f"{str(maximize).lower()} or leave it out"
        )
    unit = ARES_OBJECTIVE_UNITS[objective]
    if "objective_unit" not in config.model_fields_set:
        config.objective_unit = unit
    elif config.objective_unit != unit:
        raise ValueError(
            f"objective_unit: the ARES objective {objective!r} is in {unit!r}, not "
            f"{config.objective_unit!r} (leave objective_unit out)"
        )
    if "knob_unit" not in config.model_fields_set:
        config.knob_unit = ARES_KNOB_UNIT


def _check_trial(m: AresSimConfig) -> None:
    from pigp_torch.machines.ares_ea.simulation import load_trials

    where = "the shipped trials" if m.trials is None else str(m.trials)
    try:
        trials = load_trials(m.trials)
    except (OSError, ValueError) as err:
        raise ValueError(f"machine.trials: {err}") from None
    if m.trial not in trials:
        raise ValueError(
            f"machine.trial: no trial {m.trial} in {where} (it holds {len(trials)} trials, "
            f"keys {min(trials)}–{max(trials)})"
        )


def build_ares_machine(config: RunConfig):
    r"""The :class:`~.machine.AresMachine` of an ``ares-sim`` run: the trial
    (changed by ``model_error``), the method's objective, the screen noise and its seed, the
    run's bounds and step limit, starting at ``x_init`` (unlisted knobs: the published start,
    moved inside the run's bounds)."""
    from pigp_torch.machines.ares_ea.cases import case_machine_parts
    from pigp_torch.machines.ares_ea.machine import AresMachine
    from pigp_torch.machines.ares_ea.simulation import START_SETTING, load_trials

    m, names, bounds = config.machine, config.knob_names, config.bounds()
    trial, segment = load_trials(m.trials)[m.trial], None
    if m.model_error != "none":
        trial, segment = case_machine_parts(trial, m.model_error)
    start = dict(zip(names, START_SETTING, strict=True)) | dict(m.x_init or {})
    x_init = torch.tensor([start[n] for n in names], dtype=DTYPE)
    x_init = torch.minimum(torch.maximum(x_init, bounds[0]), bounds[1])
    return AresMachine(
        trial,
        objective=ares_objective_name(config),
        noise=m.noise,
        seed=m.seed,
        max_step=config.machine_max_step(),
        x_init=x_init,
        segment=segment,
        bounds=bounds,
    )
