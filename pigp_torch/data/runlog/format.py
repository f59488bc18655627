r"""The run log's format: tags, versions, record types, end statuses, the hash chain, and the
run log's errors and warnings.

**Hash chain** (version 3). Every record carries ``hash``, the hex sha256 of the previous
record's ``hash`` (the empty string for the header) followed by the canonical JSON of the record
without its ``hash`` (:func:`canonical_json`: keys sorted, no spaces, ASCII, floats as
``repr``):

.. math::

    h_0 = \mathrm{sha256}(c_0), \qquad h_k = \mathrm{sha256}(h_{k-1} \,\|\, c_k).

Editing, inserting, deleting or reordering a record breaks the chain at the first record
changed (or, for a deletion, at the record after the gap), so a reader names that line. The
chain is tamper-*evident*, not a signature: there is no secret, so whoever recomputes every
later hash can forge a log; and a log cut at a record boundary (a crash between two records, or
its last records removed) is a valid prefix. Logs of versions 1 and 2 have no chain: they are
read with an :class:`UnchainedLogWarning` (they cannot be verified), and only where that version
could have written them (:mod:`~pigp_torch.data.runlog.legacy`).
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import torch

#: Tag of the header record, checked on read.
FORMAT_TAG = "pigp_torch.RunLog"
FORMAT_VERSION = 3
#: Versions :func:`read_log` accepts (version 1 had no intent or discarded records, versions 1
#: and 2 no hash chain).
READABLE_VERSIONS = (1, 2, 3)
#: First version whose records carry the hash chain.
CHAINED_VERSION = 3
#: Name of the chain field of every record (version 3).
HASH_KEY = "hash"
#: Field of a record appended by this version to an older version's log (no chain).
APPENDED_KEY = "appended_by_version"
RECORD_TYPES = ("header", "start", "evaluation", "end", "intent", "discarded", "notice")
END_STATUSES = ("completed", "interrupted", "aborted", "failed")


class ReplayError(ValueError):
    """Replaying a run log did not reproduce the logged run (other config, prior or seed)."""


class LogWriteError(OSError):
    """A record could not be written to the run log (disk full, I/O error, a log left broken by
    an earlier failed write); the message names the log and the reason. Nothing of the record
    stays in the file."""


class RunLogWarning(UserWarning):
    """Something a reader of a run log should know that does not stop it (base class)."""


class TornLineWarning(RunLogWarning):
    """The last line of a run log was cut short by an interrupted write and is ignored."""


class UnchainedLogWarning(RunLogWarning):
    """The run log has no hash chain (written by an older version): it cannot be verified."""


def canonical_json(record) -> str:
    """The canonical JSON text of a record (keys sorted, no spaces, ASCII; floats as ``repr``)."""
    return json.dumps(record, sort_keys=True, separators=(",", ":"), allow_nan=False)


def chain_hash(previous: str, record: dict) -> str:
    """Hex sha256 of ``previous`` (a hash, ``""`` for the header) then the canonical JSON of
    ``record`` without its ``hash`` field."""
    body = {k: v for k, v in record.items() if k != HASH_KEY}
    return hashlib.sha256((previous + canonical_json(body)).encode("utf-8")).hexdigest()


def file_sha256(path: str | Path) -> str:
    """Hex sha256 of a file's bytes (read in 1 MiB chunks)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def floats(x) -> list[float]:
    """``x`` (a tensor or a sequence) as a flat list of Python floats."""
    if isinstance(x, torch.Tensor):
        return [float(v) for v in x.detach().reshape(-1).tolist()]
    return [float(v) for v in x]
