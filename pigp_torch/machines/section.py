r"""The building blocks of a run-file section, shared by the loop's sections and every machine
kind's (:meth:`~pigp_torch.machines.MachineKind.section`): the section base class (:class:`Section`:
unknown keys refused, no infinite or NaN number, its knob-keyed fields checked by
:meth:`Section.check_knobs`), the strict field types (:data:`Number`, :data:`Integer`,
:data:`Flag`), paths relative to the run file (:func:`resolve_path`) and the check of a mapping by
knob (:func:`same_knobs`). Light on purpose: a kind's section is imported while the run-file schema
is built.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Annotated

from pydantic import BaseModel, ConfigDict, Strict, ValidationInfo

#: A number in a run file: an int or a float, never a boolean or a string (pydantic strict mode;
#: ``true`` would otherwise run as 1 and ``"0.5"`` be converted).
Number = Annotated[float, Strict()]
#: An integer in a run file: never a boolean, a float or a string.
Integer = Annotated[int, Strict()]
#: A yes/no value in a run file: ``true`` or ``false`` only (not 1, not "yes" as a string).
Flag = Annotated[bool, Strict()]


class Section(BaseModel):
    """A section of a run file: unknown keys refused, no infinite or NaN number."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    def check_knobs(self, names: list[str]) -> None:
        """Check the section's fields keyed by knob against the run's knobs ``names`` (called
        once the whole run file is read; e.g. with :func:`same_knobs`). Default: none.

        Raises:
            ValueError: a mismatch (the message names the key).
        """


def same_knobs(key: str, mapping: dict, names: list[str], what: str = "missing knobs") -> None:
    """Check that ``mapping`` (of run-file key ``key``) names every knob of ``names`` and no other.

    Raises:
        ValueError: ``"<key>: <what> [...]"`` (knobs missing) or ``"<key>: [...] are not
            configured knobs"``.
    """
    missing = [n for n in names if n not in mapping]
    extra = [k for k in mapping if k not in names]
    if missing:
        raise ValueError(f"{key}: {what} {missing}")
    if extra:
        raise ValueError(f"{key}: {extra} are not configured knobs")


def resolve_path(path: Path | None, info: ValidationInfo) -> Path | None:
    """A path of a run file: relative paths are from the run file's folder (``base_dir`` of the
    validation context); plain text, no I/O."""
    base = (info.context or {}).get("base_dir")
    if path is None or path.is_absolute() or base is None:
        return path
    return Path(os.path.normpath(Path(base) / path))  # "a/../b" -> "b" (plain text, no I/O)
