"""pigp-torch: physics-informed Gaussian-process Bayesian optimization for particle accelerators.

The package's top level is the method's chain, one package per stage: the ring's simulation
(coupling model of a storage ring, the real SPEAR3 shipped: ``machines.ring``) -> ``data`` (datasets
drawn from it; run logs) -> ``surrogate`` (neural network) -> ``prior`` (Hessian -> precision
matrix) -> ``kernels`` and ``models`` (GPs, posteriors) -> ``optimizers`` and ``methods`` (ask/tell,
the registry) -> ``loop`` (``optimize``, run files, runs) -> ``machine`` (simulated, EPICS). The
machine kinds (``machines``: the registry ``KINDS``, one folder a kind: the ring with its benchmark,
demo, simulated EPICS servers and commands, ARES-EA) sit on the chain and use it. Around it: ``cli``
and ``commands``, ``integrations`` (Xopt, Badger), ``bench`` (the BO speed run), ``reporting``;
``_utils`` holds the plumbing every stage shares.

Performance note: the simulator multiplies many stacks of 6x6 matrices with numpy; with a
multi-threaded OpenBLAS on a busy machine, set ``OPENBLAS_NUM_THREADS=1`` before importing numpy
(the ``pigp`` command and the test suite do) — it is much faster.
"""

from pigp_torch._version import __version__

__all__ = ["__version__", "optimize"]


def __getattr__(name: str):
    """``pigp_torch.optimize`` is imported on first use, so that importing the package (and the
    ``pigp`` command's start-up) does not load torch."""
    if name == "optimize":
        from pigp_torch.loop import optimize

        return optimize
    raise AttributeError(f"module 'pigp_torch' has no attribute {name!r}")
