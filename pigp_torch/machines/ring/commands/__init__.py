"""The ring kind's ``pigp`` commands, one module each (``register(sub, bench)`` as every command
module): ``generate-data`` (:mod:`.generate_data`), ``compare`` (:mod:`.compare`), ``demo``
(:mod:`.demo`), ``serve-sim`` (:mod:`.serve_sim`), ``bench simulator`` (:mod:`.bench_simulator`)
and ``bench spear3`` (:func:`.compare.register_bench`: the same command as ``compare``), with the
options that choose a simulated ring (:mod:`.ring_options`). The ring kind adds them to ``pigp``
(:meth:`~pigp_torch.machines.ring.RingKind.register_commands` and ``register_bench``); the old
paths ``pigp_torch.commands.<name>`` import as these modules. Light: only the parsers are built
here (``pigp --help`` answers at once).
"""

from __future__ import annotations


def register_commands(sub) -> None:
    """Add ``pigp generate-data``, ``compare``, ``demo`` and ``serve-sim`` to ``sub`` (in the
    order of ``pigp --help``)."""
    from pigp_torch.machines.ring.commands import compare, demo, generate_data, serve_sim

    for module in (generate_data, compare, demo, serve_sim):
        module.register(sub, None)


def register_bench(bench) -> None:
    """Add ``pigp bench simulator`` and ``pigp bench spear3`` to ``bench``."""
    from pigp_torch.machines.ring.commands import bench_simulator, compare

    bench_simulator.register(None, bench)
    compare.register_bench(bench)
