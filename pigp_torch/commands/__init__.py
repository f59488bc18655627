"""The sub-commands of ``pigp``, one module each.

Each module listed in :data:`pigp_torch.cli.COMMAND_MODULES` defines ``register(sub, bench)``,
which adds its parsers to the top-level sub-parsers ``sub`` (``pigp NAME``) and/or to ``bench``
(``pigp bench NAME``). Heavy imports belong inside the command functions so ``pigp --help`` stays
fast.
"""
