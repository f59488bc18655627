r"""The run log: every evaluation of an online run, on disk before the next step, and its replay.

A run log is a JSON-lines file (one JSON object per line), append-only. Record types:

* ``header`` (first line, once): ``format``/``version`` tags, ``package_version``,
  ``created`` (UTC, ISO 8601), ``knob_names`` and whatever the writer adds — the command
  ``pigp optimize`` stores the validated configuration and the prior's provenance (file path,
  sha256 of its bytes, its ``provenance`` metadata).
* ``start`` (one per session: the first run and each resume): ``time``, ``initial_knobs`` (the
  knobs found on the machine, where they are put back), ``budget``, ``first_step``.
* ``intent`` (one before every ``set`` the loop sends, fsynced before the write): ``x`` (the
  setting about to be written), ``purpose`` (``"evaluation"`` or ``"restore initial"`` /
  ``"restore best"``), ``step`` (the evaluation it serves, ``null`` for a restore), ``part`` /
  ``parts`` (its place in a ramp). After a crash the last one is the last commanded setting.
* ``discarded`` (a reading thrown away because the machine's state changed during it): ``step``,
  ``y``, ``reason``, ``time``.
* ``evaluation`` (one per measurement): ``step`` (0, 1, ...), ``x`` (knob values in
  ``knob_names`` order), ``y``, ``reads`` (read attempts it took), ``t_set`` / ``t_read`` (UNIX
  times before the move and after the reading), ``ask_time_s`` and ``eval_time_s``, and
  ``reading`` (what the machine reports about the reading, e.g. the objective PV's timestamps)
  and, from a machine that measures more than its objective, ``observables`` (the values of its
  last reading, in the order of the header's ``observable_names``, units
  ``observable_units``; e.g. a screen's four beam numbers in m); in a track run (``mode:
  track``), ``tracked``: the optimizer's tracked unknowns ``{name: [value, unit]}`` when the
  setting was asked.
* ``end`` (one per session that ended in Python): ``status`` (``"completed"``,
  ``"interrupted"``, ``"aborted"`` or ``"failed"``), ``reason``, ``restored_to``,
  ``final_knobs`` (the readback after the restore), ``best``, ``n_evaluations`` and, on a machine,
  ``restored`` (whether the knobs were put back), ``last_setpoint`` (the last setting the
  machine acknowledged; ``last_intended`` the last one sent) and ``restore_attempts``.

While a :class:`RunLog` is open it holds the log's lock (:func:`pigp_torch.data.runlock.log_lock`,
``<log>.lock``): a second writer is refused with :class:`~pigp_torch.data.runlock.LockHeld`.

Each record is written with one unbuffered ``os.write``, then ``os.fsync``: a crash (even a
power cut after the call returned) loses no completed evaluation. A last line cut short by a crash
during a write (no final newline) is ignored when reading (with one
:class:`~pigp_torch.data.runlog.format.TornLineWarning`) and cut off before appending. A write that
fails (disk full) raises :class:`~pigp_torch.data.runlog.format.LogWriteError` and leaves nothing of
its record in the file; a log whose header could not be written is removed.

**Tamper evidence.** Every record carries ``hash``, a sha256 chained to the previous record's
(the header starts the chain; :mod:`pigp_torch.data.runlog.format`). :func:`read_log` verifies the
chain and refuses a log edited anywhere — a changed reading, initial knob or header bound, a line
removed or inserted — naming the first line that does not match; a version-3 log without its
hashes is refused. Logs written before the chain (versions 1 and 2) are read and resumed, with an
:class:`~pigp_torch.data.runlog.format.UnchainedLogWarning` (they cannot be verified), only
where that version could have written every record (:mod:`pigp_torch.data.runlog.legacy`: a
newer log with its version edited and its hashes deleted is refused); records appended to such a
log stay unchained and carry ``appended_by_version``. What the chain protects and what it cannot:
``docs/run_log.md``.

Why JSON lines and not CSV/Parquet: records of different types share one file, a reader needs
nothing but ``json``, appending never rewrites earlier bytes, and floats round-trip exactly
(``json`` writes ``repr(float)``).

:func:`replay` rebuilds an optimizer from the logged evaluations by re-running its asks; every
optimizer of the package is deterministic given its seed and the data told, so the rebuilt state is
the state the run had.
"""

from pigp_torch._utils import utc_now
from pigp_torch.data.runlog.format import (
    END_STATUSES,
    FORMAT_TAG,
    FORMAT_VERSION,
    READABLE_VERSIONS,
    RECORD_TYPES,
    LogWriteError,
    ReplayError,
    RunLogWarning,
    TornLineWarning,
    UnchainedLogWarning,
    chain_hash,
    file_sha256,
)
from pigp_torch.data.runlog.reader import RunRecords, read_log
from pigp_torch.data.runlog.replay import evaluation_rows, replay, tell
from pigp_torch.data.runlog.writer import RunLog

__all__ = [
    "END_STATUSES",
    "FORMAT_TAG",
    "FORMAT_VERSION",
    "READABLE_VERSIONS",
    "RECORD_TYPES",
    "LogWriteError",
    "ReplayError",
    "RunLog",
    "RunLogWarning",
    "RunRecords",
    "TornLineWarning",
    "UnchainedLogWarning",
    "chain_hash",
    "evaluation_rows",
    "file_sha256",
    "read_log",
    "replay",
    "tell",
    "utc_now",
]
