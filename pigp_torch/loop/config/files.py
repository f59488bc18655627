r"""Reading run files: YAML or JSON (a key given twice refused), validated against the schema
(:mod:`pigp_torch.loop.config.schema`); every problem is listed, one line each.
"""

from __future__ import annotations

import difflib
import json
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from pigp_torch.loop.config.schema import (
    ConfigError,
    MethodConfig,
    ObjectiveConfig,
    RunConfig,
)
from pigp_torch.loop.config.sections import SECTIONS

#: pydantic error types of a value of the wrong type in strict mode (a number, a flag).
_TYPE_ERRORS = ("float_type", "int_type", "bool_type")

_SECTIONS = {
    (): RunConfig,
    ("objective",): ObjectiveConfig,
    ("method",): MethodConfig,
}


def _allowed_keys(parent: tuple[str, ...], data: Any) -> list[str]:
    model = _SECTIONS.get(parent)
    if parent == ("machine",):
        kind = data.get("machine", {}).get("kind") if isinstance(data, dict) else None
        model = SECTIONS.get(kind)
    return list(model.model_fields) if model is not None else []


def format_errors(err: ValidationError, data: Any) -> list[str]:
    """One line per problem of a pydantic ``ValidationError`` (unknown keys with the closest
    allowed one)."""
    lines = []
    for e in err.errors():
        loc = [str(p) for p in e["loc"]]
        if len(loc) >= 2 and loc[0] == "machine" and loc[1] in SECTIONS:
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
            if e["type"] in _TYPE_ERRORS:
                msg += f", got {e['input']!r} (booleans and quoted text are not numbers)"
            line = f"{where}: {msg}" if where else msg
        lines.append(line)
    return lines


def parse_config(data: Any, *, base_dir: str | Path | None = None, source: str = "config"):
    r"""Validate a configuration mapping against the schema; returns a :class:`RunConfig`.

    The method and the prior file are not checked here (:func:`pigp_torch.loop.run.validate_config`
    checks them).

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
        raise invalid(source, format_errors(err, data)) from None


def invalid(source: str, lines: list[str]) -> ConfigError:
    """The :class:`ConfigError` listing ``lines`` (one problem each) of configuration
    ``source``."""
    if len(lines) == 1:
        return ConfigError(f"{source}: invalid run configuration: " + lines[0])
    return ConfigError(f"{source}: invalid run configuration:\n  - " + "\n  - ".join(lines))


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


def read_run_file(path: str | Path) -> Any:
    r"""Read a run file (``.json``: JSON, anything else: YAML, safe loader); returns the parsed
    data (not validated).

    Raises:
        FileNotFoundError: no such file.
        ConfigError: a folder, a file that cannot be read (permissions, not UTF-8 text), not
            valid YAML/JSON, or a key given twice.
    """
    path = Path(path)
    if path.is_dir():
        raise ConfigError(f"{path} is a folder, not a run file (give the YAML or JSON file)")
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise
    except OSError as err:
        raise ConfigError(f"{path}: cannot read the run file: {err.strerror or err}") from None
    except UnicodeDecodeError as err:
        raise ConfigError(f"{path}: not a text file (UTF-8): {err.reason}") from None
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
    return data
