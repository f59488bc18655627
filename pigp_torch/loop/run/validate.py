r"""A run file checked as a whole: the schema (:mod:`pigp_torch.loop.config`), then the method
against the registry (:mod:`pigp_torch.methods`: a run-file method, known options, a prior file and
a maximized objective for the methods built from the physics prior), then every machine kind's
checks (:meth:`pigp_torch.machines.MachineKind.check_run`: a kind's methods run on its machine
only; its section against its simulation), then the prior file (its knobs must be the run's, same
names in the same order).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from pigp_torch.loop.config import RunConfig, invalid, parse_config, read_run_file
from pigp_torch.machines import KINDS
from pigp_torch.methods import METHODS, run_file_methods
from pigp_torch.prior import PhysicsPrior


def _choices(names: tuple[str, ...]) -> str:
    quoted = [repr(n) for n in names]
    return ", ".join(quoted[:-1]) + " or " + quoted[-1] if len(quoted) > 1 else quoted[0]


def check_method(config: RunConfig) -> None:
    """Check ``config.method`` against the registry (name, option names; a prior file and a
    maximized objective where the method needs the physics prior).

    Raises:
        ValueError: the first problem found (its message names the key).
    """
    method, names = config.method, run_file_methods()
    if method.name not in names:
        raise ValueError(f"method.name: Input should be {_choices(names)}")
    spec = METHODS[method.name]
    allowed = spec.option_names()
    unknown = sorted(set(method.options) - allowed)
    if unknown:
        raise ValueError(
            f"method.options: unknown option(s) {unknown} for {method.name} "
            f"(allowed: {', '.join(sorted(allowed))})"
        )
    problems = _option_type_problems(spec, method.options)
    if problems:
        raise ValueError(f"method.options: {'; '.join(problems)}")
    if spec.needs_prior and not config.objective.maximize:
        raise ValueError(
            f"method {method.name} needs objective.maximize: true "
            "(the physics prior describes a peak)"
        )
    if spec.needs_prior and config.prior is None:
        raise ValueError(f"prior: method {method.name} needs a prior file (pigp build-prior)")


def _option_defaults(spec) -> dict[str, Any]:
    """Default value of each option of ``spec`` that has one (the builder's keywords, then those
    of the classes it forwards to)."""
    import inspect

    allowed, out = spec.option_names(), {}
    for func in (spec.builder, *(cls.__init__ for cls in spec.forwards_to)):
        for p in inspect.signature(func).parameters.values():
            if p.name in allowed and p.default is not p.empty:
                out.setdefault(p.name, p.default)
    return out


def _is_number_text(value: Any) -> bool:
    if not isinstance(value, str):
        return False
    try:
        float(value)
    except ValueError:
        return False
    return True


def _option_type_problems(spec, options: dict[str, Any]) -> list[str]:
    """Options whose value is of the wrong kind, one line each: a quoted number anywhere, a
    boolean where the builder's default is a number, anything but ``true``/``false`` where it
    is a flag (numbers must be numbers, as everywhere in a run file)."""
    defaults, problems = _option_defaults(spec), []
    for name, value in options.items():
        default = defaults.get(name)
        number = isinstance(default, (int, float)) and not isinstance(default, bool)
        if _is_number_text(value):
            problems.append(f"{name}: {value!r} is quoted text; write the number without quotes")
        elif number and isinstance(value, bool):
            problems.append(f"{name}: {value!r} is not a number (default {default!r})")
        elif isinstance(default, bool) and not isinstance(value, bool):
            problems.append(f"{name}: {value!r} is not true or false (default {default!r})")
    return problems


def load_prior(path: Path, names: list[str]) -> PhysicsPrior:
    """The prior file at ``path``, for the knobs ``names`` (same names, same order).

    Raises:
        ValueError: no such file, not a prior file, or other knobs.
    """
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


def validate_config(data: Any, *, base_dir: str | Path | None = None, source: str = "config"):
    r"""Validate a configuration mapping as a whole; returns a
    :class:`~pigp_torch.loop.config.RunConfig` with its prior loaded
    (:meth:`~pigp_torch.loop.config.RunConfig.get_prior`).

    Args:
        data: the parsed file (a mapping).
        base_dir: folder that relative paths are taken from (``None``: as given).
        source: name used in error messages (the file name).

    Raises:
        ConfigError: every problem of the schema, one per line; then the first problem of the
            method or the prior file.
    """
    config = parse_config(data, base_dir=base_dir, source=source)
    try:
        check_method(config)
        for kind in KINDS.values():
            kind.check_run(config, METHODS[config.method.name])
        if config.prior is not None:
            config.attach_prior(load_prior(config.prior, config.knob_names))
    except ValueError as err:
        raise invalid(source, [str(err)]) from None
    return config


def load_config(path: str | Path) -> RunConfig:
    r"""Read a run file (``.json``: JSON, anything else: YAML, safe loader) and validate it
    (:func:`validate_config`).

    Relative ``prior``, ``log`` and ``lock_dir`` paths are taken relative to the file's folder.

    Raises:
        FileNotFoundError: no such file.
        ConfigError: unreadable or invalid configuration (every problem, one per line), or a key
            given twice.
    """
    path = Path(path)
    data = read_run_file(path)
    return validate_config(data, base_dir=path.parent.absolute(), source=str(path))
