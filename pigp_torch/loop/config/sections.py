r"""The ``machine`` section of a run file, chosen by its ``kind``: the loop's own section
(``epics``: a machine over EPICS) and the section of every machine kind of
:data:`pigp_torch.machines.KINDS` that has a simulated machine (``ares-sim``, ``sim``: the ring).
"""

from __future__ import annotations

from typing import Annotated, Union

from pydantic import Field

from pigp_torch.loop.config.machines import EpicsMachineConfig
from pigp_torch.machines import KINDS


def machine_sections() -> dict[str, type]:
    """``machine.kind -> section class``: each machine kind's own (registry order), then
    ``epics``."""
    sections: dict[str, type] = {}
    for kind in KINDS.values():
        if kind.run_file_kind is not None and kind.run_file_kind not in sections:
            sections[kind.run_file_kind] = kind.section()
    return {**sections, "epics": EpicsMachineConfig}


#: ``machine.kind -> section class`` (:func:`machine_sections`, found once at import).
SECTIONS: dict[str, type] = machine_sections()

#: The ``machine`` section of a run file: one of :data:`SECTIONS`, by ``kind``.
MachineConfig = Annotated[Union[tuple(SECTIONS.values())], Field(discriminator="kind")]  # noqa: UP007
