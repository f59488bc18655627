"""``pigp badger-setup``: make Badger list ``pigp_physics`` and the ``pigp_sim`` environment."""

from __future__ import annotations


def cmd_badger_setup(args) -> int:
    from pigp_torch.integrations.badger import cmd_setup

    return cmd_setup(args)


def register(sub, bench) -> None:
    """Add ``pigp badger-setup`` to the top-level sub-parsers ``sub`` (nothing under ``bench``)."""
    from pigp_torch.integrations.badger import (
        SETUP_DESCRIPTION,
        SETUP_HELP,
        add_setup_arguments,
    )

    p = sub.add_parser("badger-setup", help=SETUP_HELP, description=SETUP_DESCRIPTION)
    add_setup_arguments(p)
    p.set_defaults(func=cmd_badger_setup)
