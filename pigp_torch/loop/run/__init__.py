"""A run of ``pigp optimize``: validating a run file as a whole
(:mod:`~pigp_torch.loop.run.validate`), building the optimizer, machine and log header
(:mod:`~pigp_torch.loop.run.build`; a machine kind's simulated machine through
:data:`pigp_torch.machines.KINDS`) and continuing a logged run
(:mod:`~pigp_torch.loop.run.resume`)."""

from pigp_torch.loop.run.build import (
    RunSetup,
    build_machine,
    build_optimizer,
    build_run,
    machine_kind,
    prior_record,
)
from pigp_torch.loop.run.resume import advance_simulated_noise, check_resume, logged_config
from pigp_torch.loop.run.validate import check_method, load_config, load_prior, validate_config

__all__ = [
    "RunSetup",
    "advance_simulated_noise",
    "build_machine",
    "build_optimizer",
    "build_run",
    "check_method",
    "check_resume",
    "load_config",
    "load_prior",
    "logged_config",
    "machine_kind",
    "prior_record",
    "validate_config",
]
