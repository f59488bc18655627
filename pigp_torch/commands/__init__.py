"""The sub-commands of ``pigp``, one module each.

Each module listed in :data:`pigp_torch.cli.COMMAND_MODULES` defines ``register(sub, bench)``,
which adds its parsers to the top-level sub-parsers ``sub`` (``pigp NAME``) and/or to ``bench``
(``pigp bench NAME``). Heavy imports belong inside the command functions so ``pigp --help`` stays
fast.

The ring kind's commands (``compare``, ``demo``, ``serve-sim``, ``generate-data``, ``bench
simulator``) and their ring options live in its folder, :mod:`pigp_torch.machines.ring.commands`;
``pigp_torch.commands.<name>`` imports as that module itself.
"""

from pigp_torch._utils.aliases import alias_package

alias_package(__name__, "pigp_torch.machines.ring.commands")
