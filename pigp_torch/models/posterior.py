r"""The posterior part of the Bayesian-optimization core: a protocol and its prediction record.

A posterior is what the optimizer knows about the objective after the readings told so far, in
the optimizer's internal, maximized sign. Every implementation returns the mean :math:`\mu` and
the standard deviation :math:`\sigma` of the latent objective (no observation noise) at ``N x d``
settings in knob units, and where it can their derivatives in :math:`\mathbf x`:

* :class:`~pigp_torch.models.incremental_gp.IncrementalPosterior`: exact GP of a fixed
  full-precision RBF kernel grown one reading at a time (orders 0, 1, 2);
* :class:`~pigp_torch.models.physics_posterior.PhysicsFormPosterior`: the online-fitted
  inverse-square-root form plus its residual GP, with the prior check (orders 0, 1);
* :class:`~pigp_torch.models.botorch_posterior.BoTorchPosterior`: any BoTorch ``Model`` built
  by a factory at every fit (orders 0, 1 by autograd); BoTorch acquisition objects use its
  ``model`` as they are.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np
from torch import Tensor


@dataclass
class Prediction:
    r"""Posterior mean and standard deviation at ``N`` settings and their derivatives.

    ``mean``, ``std``: ``N``; ``dmean``, ``dstd``: ``N x d`` (order >= 1); ``hmean``, ``hstd``:
    ``N x d x d`` (order 2); all float64 NumPy arrays in knob units, ``None`` when not asked.
    """

    mean: np.ndarray
    std: np.ndarray
    dmean: np.ndarray | None = None
    dstd: np.ndarray | None = None
    hmean: np.ndarray | None = None
    hstd: np.ndarray | None = None

    @property
    def variance(self) -> np.ndarray:
        r""":math:`\sigma^2` (``N``)."""
        return self.std**2


@runtime_checkable
class Posterior(Protocol):
    """What :class:`~pigp_torch.optimizers.bo.BayesianOptimizer` needs of a posterior.

    ``observe`` is called at every tell (an incremental posterior updates there), ``fit`` at
    every ask with all readings (``X: n x d``, ``Y: n``, internal sign); ``max_order`` is the
    highest derivative :meth:`predict` gives.
    """

    max_order: int

    def observe(self, x: Tensor, y: float) -> None: ...

    def fit(self, X: Tensor, Y: Tensor) -> None: ...

    def predict(self, X: np.ndarray, order: int = 0) -> Prediction: ...

    def train_mean(self, X: Tensor) -> np.ndarray: ...

    def extra_starts(self, box: Tensor) -> list[Tensor]: ...

    def info(self) -> dict: ...


class PosteriorBase:
    """Defaults of the :class:`Posterior` protocol: nothing to do at a tell, no extra starts of
    the acquisition search, no information for ``last_info``, no notices."""

    max_order = 1

    def observe(self, x: Tensor, y: float) -> None:
        """Nothing to update per reading (the posterior is built at :meth:`fit`)."""

    def extra_starts(self, box: Tensor) -> list[Tensor]:
        """Settings (``d`` each) the acquisition search should start from besides its own."""
        return []

    def info(self) -> dict:
        """Entries for the optimizer's ``last_info`` after a fit."""
        return {}

    def take_notices(self) -> list[dict]:
        """Notices for the operator made since the last call (``kind``, ``message``, data)."""
        return []
