r"""Continuing a logged run: the logged configuration (verified by its digest), the check that a
run file matches it, and the simulated machine's noise stream put where the run left it.
"""

from __future__ import annotations

from pigp_torch.data.runlog import file_sha256
from pigp_torch.loop.config import ConfigError, RunConfig, config_digest
from pigp_torch.loop.run.validate import validate_config


def check_resume(config: RunConfig, records) -> None:
    r"""Check that a run log comes from this configuration, so that it can be continued.

    The logged configuration must equal ``config`` except ``budget`` (which may grow) and
    ``log``; the prior file must still have the logged sha256.

    Raises:
        ConfigError: the configurations differ (the keys are named) or the prior changed.
    """
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

    A simulated machine draws its noise from a seeded generator; ``machine.advance_noise(n_reads)``
    (the :class:`~pigp_torch.machine.base.Machine` protocol) moves the stream on as ``n_reads``
    readings would (one normal variate per reading on the ring's
    :class:`~pigp_torch.machine.SimulatedMachine`, four on the ARES-EA screen), so a resumed
    simulated run sees the noise an uninterrupted one would have. Other machines do nothing.
    """
    machine.advance_noise(int(n_reads))
