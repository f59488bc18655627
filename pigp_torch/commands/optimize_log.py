"""The run log and the locks of ``pigp optimize``: the locks to take, the log's folder checked,
an existing log described, a log to continue read (hash chain verified)."""

from __future__ import annotations

from pathlib import Path

from pigp_torch.commands.optimize_output import say


def _locks(config, log_path: Path):
    """The run's locks, not yet taken: the log's, then one per PV prefix (EPICS)."""
    from pigp_torch.data.runlock import log_lock, machine_locks

    locks = [log_lock(log_path)]
    pvs = config.pv_names()
    if pvs:
        locks += machine_locks(pvs, config.lock_dir)
    return locks


def _check_log_folder(path: Path) -> None:
    """The run log's folder is (or can be made) a writable folder.

    Raises:
        ValueError: the path is no place for a log (a file where its folder should be, a
            folder given as the log): invalid input.
        PermissionError: the folder is not writable (the log cannot be started, as on a full
            disk).
    """
    import os

    folder = path.parent
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    if not folder.is_dir():
        raise ValueError(f"the run log {path} cannot be created: {folder} is not a folder")
    if not os.access(folder, os.W_OK | os.X_OK):
        import errno

        raise PermissionError(  # like a full disk: the log cannot be started (exit 1)
            errno.EACCES, f"the run log {path} cannot be created: {folder} is not writable"
        )
    if path.is_dir():
        raise ValueError(f"the run log {path} is a folder; give a file name")


def _existing_log(path: Path) -> str:
    """What an existing run log at ``path`` holds, in words (for the refusal and the dry run)."""
    from pigp_torch.data.runlog import read_log

    try:
        records = read_log(path, warn=False)
    except (ValueError, OSError) as err:
        return f"it is not a run log that can be continued ({err})"
    end = records.last_end
    how = "ended " + end["status"] if end is not None else "no end record (a crash)"
    return f"it holds {records.n_evaluations} evaluation(s), {how}"


def _read_resumed(path: Path, *, warn_out=None):
    """The run log to continue, read and its hash chain verified; its warnings (a torn last
    line, no chain) are printed once, one plain line each, to ``warn_out``."""
    from pigp_torch.data.runlog import read_log

    records = read_log(path, warn=False)
    if warn_out is not None:
        for note in records.warnings:
            say(warn_out, f"warning: {note}")
    return records


def unverified_target(setup, records) -> str | None:
    """Why a log without a hash chain (an older version's) may not restore to its logged
    initial knobs without confirmation: they cannot be verified, and they differ from the
    machine's setpoints now by more than the run's step limit (``None``: no chain needed, or
    within the step limit)."""
    import torch

    from pigp_torch.loop import effective_max_step
    from pigp_torch.loop.moves import setpoints_of

    initial = records.initial_knobs
    if records.chained or initial is None:
        return None
    now = setpoints_of(setup.machine)
    bounds = setup.config.bounds()
    limit = effective_max_step(setup.machine, bounds, setup.config.machine_max_step())
    delta = (torch.tensor(initial, dtype=now.dtype) - now).abs()
    far = delta > (limit if limit is not None else torch.full_like(delta, float("inf")))
    if not bool(far.any()):
        return None
    names = [n for n, f in zip(setup.config.knob_names, far.tolist(), strict=True) if f]
    return (
        f"{records.path} has no hash chain (run-log version {records.header.get('version')}): "
        f"its restore target (the initial knobs above) cannot be verified and is more than "
        f"max_step from the setpoints now for {', '.join(names)}; refused, nothing was moved "
        "(check the target, then resume with --accept-restore-target to restore there)"
    )
