"""Data of the chain: the shipped lattice decks (``*.json``) and physics prior (``priors/``,
:func:`builtin_prior`; provenance of both in README.md),
training sets drawn from a simulator (:mod:`~pigp_torch.data.dataset`,
:mod:`~pigp_torch.data.sampling`), and run logs with their locks
(:mod:`~pigp_torch.data.runlog`, :mod:`~pigp_torch.data.runlock`).

Importing this package imports none of its modules (the lock module stays light).
"""

from pathlib import Path

#: The physics priors shipped with the package (provenance in ``data/README.md``), by the name a
#: run file gives after ``builtin:`` (``prior: builtin:spear3``).
BUILTIN_PRIORS: dict[str, str] = {"spear3": "priors/spear3.json"}

#: The prefix that names a shipped prior instead of a file path.
BUILTIN_PREFIX = "builtin:"


def builtin_prior(reference: str) -> Path:
    """The file of the shipped prior ``reference`` (``"builtin:spear3"`` or ``"spear3"``).

    Raises:
        ValueError: no shipped prior has that name (the message lists the names).
    """
    name = str(reference).removeprefix(BUILTIN_PREFIX)
    if name not in BUILTIN_PRIORS:
        known = ", ".join(BUILTIN_PREFIX + k for k in BUILTIN_PRIORS)
        raise ValueError(f"no shipped prior {reference!r}; the package ships {known}")
    return Path(__file__).resolve().parent / BUILTIN_PRIORS[name]
