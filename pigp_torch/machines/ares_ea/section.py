r"""The run-file section of the simulated ARES-EA linac: ``machine: {kind: ares-sim, trial: ...}``
(:class:`AresSimConfig`)."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field, ValidationInfo, field_validator

from pigp_torch.machines.section import Integer, Number, Section, resolve_path


class AresSimConfig(Section):
    r"""The simulated ARES-EA linac segment (DESY): one published trial tracked through Cheetah
    behind :class:`~.machine.AresMachine` (five magnets, one screen).

    The run's knobs must be the five ARES knobs in the segment's order (``AREAMQZM1``,
    ``AREAMQZM2``, ``AREAMCVM1``, ``AREAMQZM3``, ``AREAMCHM1``: k1 in 1/m², angles in rad) with
    bounds inside the magnets' ranges; each reading measures the four beam numbers on the screen
    (:math:`\mu_x, \sigma_x, \mu_y, \sigma_y` in m, the run's *observables*) and returns the
    objective the method reads (``ares-physics``: the mean absolute error to the trial's target in
    m, minimized; ``published-nm``: that error with a 100× weight off the screen, minimized;
    any other method: the published BO's reward, maximized). These checks need the simulation
    and the method registry and are made by :func:`pigp_torch.loop.run.validate_config`.

    Attributes:
        trial: the trial's key in the trials file (required; the incoming beam, misalignments
            and target of the simulated machine).
        trials: a trials file in the published YAML format (relative paths from the run file's
            folder); default ``None``: the shipped trials 0–149.
        noise: screen noise, the standard deviation of each of the four beam numbers (m,
            default 0: noise-free as published).
        seed: seed of the noise stream.
        model_error: the wrong-model case of the simulated machine (default ``"none"``: the
            trial as published; :data:`~.cases.MODEL_ERROR_CASES`).
        x_init: knob values the machine starts at, by knob name (unlisted knobs: the published
            start 10, −10, 0, 10, 0).
    """

    kind: Literal["ares-sim"]
    trial: Integer
    trials: Path | None = None
    noise: Number = Field(0.0, ge=0.0)
    seed: Integer = 0
    model_error: str = "none"
    x_init: dict[str, Number] | None = None

    @field_validator("trials")
    @classmethod
    def _resolve_trials(cls, path: Path | None, info: ValidationInfo) -> Path | None:
        return resolve_path(path, info)
