"""Run files of ``pigp optimize``: the schema (:mod:`~pigp_torch.loop.config.schema`) and reading
(:mod:`~pigp_torch.loop.config.files`). Nothing here imports a layer above ``_utils``; the run is
checked against the method registry and built by :mod:`pigp_torch.loop.run`."""

from pigp_torch.loop.config.files import format_errors, invalid, parse_config, read_run_file
from pigp_torch.loop.config.schema import (
    ConfigError,
    EpicsMachineConfig,
    MachineConfig,
    MethodConfig,
    ObjectiveConfig,
    RunConfig,
    config_digest,
)

__all__ = [
    "ConfigError",
    "EpicsMachineConfig",
    "MachineConfig",
    "MethodConfig",
    "ObjectiveConfig",
    "RunConfig",
    "config_digest",
    "format_errors",
    "invalid",
    "parse_config",
    "read_run_file",
]
