r"""What a run log of an older version (1 or 2, before the hash chain) could hold: a log that
claims such a version is read only where every record could have been written by it.

Versions 1 and 2 carry no hash chain, so "version 2, no hashes" is also what a newer log looks
like after its ``version`` was edited and every ``hash`` deleted (to edit it unnoticed). Such a
downgraded log gives itself away by what the older writers never wrote: the record types (version
1 had no ``intent``, ``discarded`` or ``notice`` records), the fields of each record type, and
the keys of the run configuration stored in the header (the run-file options of that time; a
newer ``pigp optimize`` stores every option it knows, with its default). :func:`check_legacy`
refuses a log with anything newer, naming the line and the field.

The field sets below are those the writers of versions 1 and 2 produced (the run log, the loop
and ``pigp optimize`` as they were then); ``notice`` records carry whatever an optimizer reported
and are not restricted beyond their type. A record that a newer version appended when it
resumed such a log carries ``appended_by_version`` (and is not restricted either); the header and
the first session's records never do, and no record the older version wrote may follow one.
"""

from __future__ import annotations

from pathlib import Path

from pigp_torch.data.runlog.format import APPENDED_KEY, FORMAT_VERSION

#: Record types of each version without a chain.
LEGACY_TYPES = {
    1: ("header", "start", "evaluation", "end"),
    2: ("header", "start", "evaluation", "end", "intent", "discarded", "notice"),
}
#: Fields each record type had in versions 1 and 2 (``type`` included).
LEGACY_FIELDS = {
    "header": {"type", "format", "version", "package_version", "created", "knob_names",
               "method", "bounds", "maximize", "config", "config_sha256", "prior", "budget"},
    "start": {"type", "time", "initial_knobs", "budget", "first_step", "found_knobs"},
    "intent": {"type", "time", "x", "purpose", "step", "part", "parts"},
    "discarded": {"type", "step", "y", "reason", "time"},
    "evaluation": {"type", "step", "x", "y", "reads", "t_set", "t_read", "ask_time_s",
                   "eval_time_s", "reading"},
    "end": {"type", "time", "status", "reason", "restored_to", "final_knobs", "n_evaluations",
            "best", "restored", "last_setpoint", "restore_attempts", "restore_errors",
            "deferred_signals", "restore_error"},
}  # fmt: skip
#: Keys of the run configuration a version-1/2 header stored, by section.
LEGACY_CONFIG = {
    "": {"machine", "knobs", "objective", "method", "prior", "budget", "max_step", "log",
         "restore", "read_retries", "retry_interval", "objective_floor", "readback_tolerance",
         "restore_attempts", "restore_interval", "lock_dir"},
    "objective": {"pv", "maximize"},
    "method": {"name", "seed", "options"},
    "machine:sim": {"kind", "error_seed", "optics", "noise", "seed", "x_init"},
    "machine:epics": {"kind", "protocol", "setpoint_pvs", "readback_pvs", "setpoint_suffix",
                      "readback_suffix", "settle_time", "tolerance", "tolerance_fraction",
                      "n_average", "average_interval", "timeout", "stale_timeout"},
}  # fmt: skip


def _newer(keys, allowed: set[str]) -> list[str]:
    return sorted(str(k) for k in keys if k not in allowed)


def _check_config(config, where: str) -> None:
    """The header's ``config`` holds only the options of that time."""
    if config is None:
        return
    if not isinstance(config, dict):
        raise ValueError(f"{where}: the header's config is not a mapping")
    problems = [f"config {k}" for k in _newer(config, LEGACY_CONFIG[""])]
    for section in ("objective", "method"):
        value = config.get(section)
        if isinstance(value, dict):
            problems += [f"config {section}.{k}" for k in _newer(value, LEGACY_CONFIG[section])]
    machine = config.get("machine")
    if isinstance(machine, dict):
        kind = machine.get("kind")
        allowed = LEGACY_CONFIG.get(f"machine:{kind}")
        if allowed is None:
            problems.append(f"config machine.kind {kind!r}")
        else:
            problems += [f"config machine.{k}" for k in _newer(machine, allowed)]
    if problems:
        raise ValueError(f"{where}: {', '.join(problems)}")


def check_legacy(records: list[dict], version: int, path: Path) -> None:
    """Refuse a log claiming ``version`` (1 or 2) whose content that version could not have
    written: a ``hash`` anywhere, a record type or a field it did not have, a run-file option
    in the header's configuration that did not exist then.

    Raises:
        ValueError: naming the line and what is newer than ``version``.
    """
    types = LEGACY_TYPES[version]
    appended, starts = False, 0
    for k, rec in enumerate(records, start=1):
        kind = rec.get("type")
        where = f"{path}:{k}"
        prefix = f"{where}: the log claims run-log version {version} (no hash chain) but"
        starts += kind == "start"
        if APPENDED_KEY in rec:
            if kind == "header" or starts < 2 or rec[APPENDED_KEY] != FORMAT_VERSION:
                raise ValueError(
                    f"{prefix} its {kind} record claims to be appended by version "
                    f"{rec[APPENDED_KEY]!r} (the log was edited); refused"
                )
            appended = True
            continue
        if appended:
            raise ValueError(
                f"{prefix} its {kind} record follows records appended by a newer version "
                "without saying so (the log was edited); refused"
            )
        if kind not in types:
            raise ValueError(
                f"{prefix} holds a {kind!r} record, which that version did not write (the log "
                "was edited); refused"
            )
        if kind == "notice":
            continue
        newer = _newer(rec, LEGACY_FIELDS[kind])
        if newer:
            raise ValueError(
                f"{prefix} its {kind} record has field(s) {', '.join(newer)}, written only by "
                "newer versions (the log was edited); refused"
            )
        if kind == "header":
            try:
                _check_config(rec.get("config"), where)
            except ValueError as err:
                raise ValueError(
                    f"{prefix} its header stores option(s) that version did not have "
                    f"({str(err).split(': ', 1)[1]}): the log was edited; refused"
                ) from None
