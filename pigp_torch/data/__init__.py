"""Data of the chain: the shipped lattice decks (``*.json``, provenance in README.md),
training sets drawn from a simulator (:mod:`~pigp_torch.data.dataset`,
:mod:`~pigp_torch.data.sampling`), and run logs with their locks
(:mod:`~pigp_torch.data.runlog`, :mod:`~pigp_torch.data.runlock`).

Importing this package imports none of its modules (the lock module stays light).
"""
