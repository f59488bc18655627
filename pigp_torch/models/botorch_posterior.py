r"""Any BoTorch model as a posterior of the Bayesian-optimization core.

:class:`BoTorchPosterior` builds a BoTorch ``Model`` from all readings at every fit through a
factory (e.g. :func:`~pigp_torch.models.physics_informed_gp` or
:func:`~pigp_torch.models.ml2_gp`); BoTorch acquisition objects take its :attr:`model` as they
are, and :meth:`~BoTorchPosterior.predict` gives the mean and standard deviation of
``model.posterior`` with their gradients by autograd, so the core's own acquisitions run on it
too.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch
from botorch.models.model import Model

from pigp_torch.models.posterior import PosteriorBase, Prediction


class BoTorchPosterior(PosteriorBase):
    r"""A BoTorch model rebuilt from all readings at every :meth:`fit`.

    Args:
        factory: ``(X: n x d, Y: n x 1) -> Model`` (float64; ``Y`` in the internal, maximized
            sign).
    """

    #: BoTorch draws from torch's global RNG: the core seeds a forked one per ask.
    uses_torch_rng = True

    max_order = 1

    def __init__(self, factory: Callable[[torch.Tensor, torch.Tensor], Model]) -> None:
        if not callable(factory):
            raise ValueError("model must be a callable (X: n x d, Y: n x 1) -> botorch Model")
        self.factory = factory
        self.model: Model | None = None

    def fit(self, X: torch.Tensor, Y: torch.Tensor) -> None:
        """Build the model from ``X: n x d`` and ``Y: n``."""
        model = self.factory(X, Y.reshape(-1, 1))
        if not isinstance(model, Model):
            raise ValueError(f"model factory returned {type(model).__name__}, not a Model")
        self.model = model

    def train_mean(self, X: torch.Tensor) -> torch.Tensor:
        """Posterior mean at the told points ``X`` (``n``)."""
        with torch.no_grad():
            return self.model.posterior(X).mean.reshape(-1)

    def predict(self, X: np.ndarray, order: int = 0) -> Prediction:
        r"""Mean and standard deviation of ``model.posterior`` at ``X: N x d`` (each point its
        own batch, as BoTorch's analytic acquisitions see it); ``order=1`` adds their gradients
        by autograd. :math:`\sigma = \sqrt{\max(\sigma^2, 10^{-12})}` (BoTorch's ``min_var``)."""
        if order not in (0, 1):
            raise ValueError(f"a BoTorch posterior gives orders 0 and 1 here, got {order}")
        x = torch.as_tensor(np.asarray(X, dtype=np.float64)).clone().requires_grad_(order == 1)
        with torch.enable_grad() if order else torch.no_grad():
            post = self.model.posterior(x.unsqueeze(-2))
            mean = post.mean.reshape(-1)
            std = post.variance.reshape(-1).clamp_min(1e-12).sqrt()
            if order == 0:
                return Prediction(mean.numpy(), std.numpy())
            (dmean,) = torch.autograd.grad(mean.sum(), x, retain_graph=True)
            (dstd,) = torch.autograd.grad(std.sum(), x)
        return Prediction(mean.detach().numpy(), std.detach().numpy(), dmean.numpy(), dstd.numpy())
