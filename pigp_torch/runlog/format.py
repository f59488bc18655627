r"""The run log's format: tags, versions, record types and end statuses, and small helpers."""

from __future__ import annotations

import hashlib
from pathlib import Path

import torch

#: Tag of the header record, checked on read.
FORMAT_TAG = "pigp_torch.RunLog"
FORMAT_VERSION = 2
#: Versions :func:`read_log` accepts (version 1 had no intent or discarded records).
READABLE_VERSIONS = (1, 2)
RECORD_TYPES = ("header", "start", "evaluation", "end", "intent", "discarded", "notice")
END_STATUSES = ("completed", "interrupted", "aborted", "failed")


class ReplayError(ValueError):
    """Replaying a run log did not reproduce the logged run (other config, prior or seed)."""


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
