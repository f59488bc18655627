r"""Bayesian optimization on a BoTorch model, as a recipe of the core.

:class:`BayesOpt` is :class:`~pigp_torch.optimizers.bo.BayesianOptimizer` with a
:class:`~pigp_torch.models.botorch_posterior.BoTorchPosterior` (a BoTorch model rebuilt from all
readings at every ask through a user-given factory, e.g. the physics-informed GP whose kernel is
fixed in advance), a BoTorch analytic acquisition, BoTorch's ``optimize_acqf`` as the search and
the trust box: the knob bounds intersected with a box of half-width ``step_limit`` (in normalized
knob units) around a centre point. The step limit is part of the method (a fixed-kernel UCB
without it wanders to the corners of a 13-D box) and a safety rule on a real machine.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from botorch.models.model import Model

from pigp_torch._utils import check_bounds
from pigp_torch.models.botorch_posterior import BoTorchPosterior
from pigp_torch.optimizers.bo import BayesianOptimizer, BOParts, OptimizeAcqf, TrustRegion
from pigp_torch.optimizers.bo.acquisition import (
    ACQUISITIONS,
    BoTorchAcquisition,
    botorch_analytic,
)
from pigp_torch.optimizers.bo.defaults import BO_DEFAULTS
from pigp_torch.optimizers.bo.region import TRUST_CENTERS

__all__ = ["ACQUISITIONS", "TRUST_CENTERS", "BayesOpt"]


class BayesOpt(BayesianOptimizer):
    r"""GP Bayesian optimization with UCB / EI acquisition restricted to a trust box.

    **Model.** ``model(X, Y)`` is called at every :meth:`ask` with all data told so far,
    ``X: n x d`` and ``Y: n x 1`` (float64), and must return a BoTorch ``Model``. Internally the
    optimizer always *maximizes*: with ``maximize=False`` it passes ``Y = -y`` to the factory, so
    the model sees the negated objective (a prior mean in the factory must then be negated too).

    **Acquisition** (BoTorch's, on the internal, maximized objective, posterior mean
    :math:`\mu`, standard deviation :math:`\sigma`, best observed value :math:`y^*`):

    * ``"ucb"``: :math:`\mu(x) + \sqrt{\beta}\,\sigma(x)` (BoTorch convention; ``beta=4`` is the
      authors' :math:`\mu + 2\sigma`);
    * ``"ei"``: :math:`E[\max(g(x) - y^*, 0)]`; ``"logei"``: its numerically robust logarithm.

    **Trust box** (:class:`~pigp_torch.optimizers.bo.region.TrustRegion`): half-width
    ``step_limit`` of each knob's half-range around the centre, ``"best_observed"`` (the best
    noisy reading, first one on ties) or ``"best_mean"`` (the told point of highest posterior
    mean); ``step_limit=None`` searches the whole knob box. The proposal is clamped into the box.

    **Determinism.** Each ask seeds a forked torch RNG with ``seed + n_told``.

    ``last_info`` as :class:`~pigp_torch.optimizers.bo.BayesianOptimizer`'s; ``last_model`` is
    the model of the last ask.

    Defaults: :data:`~pigp_torch.optimizers.bo.defaults.BO_DEFAULTS`.

    Args:
        bounds: ``2 x d`` knob bounds.
        model: factory ``(X: n x d, Y: n x 1) -> Model``.
        acquisition: ``"ucb"``, ``"ei"``, ``"logei"``, or any BoTorch acquisition as a
            callable ``(model, best_f) -> AcquisitionFunction`` (``best_f``: the best reading,
            internal sign), e.g. ``lambda m, b: ProbabilityOfImprovement(m, best_f=b)``.
        beta: UCB trade-off :math:`\beta \ge 0`.
        step_limit: trust-box half-width as a fraction of each knob's half-range, or ``None``.
        trust_center: ``"best_observed"`` or ``"best_mean"``.
        maximize: maximize (default) or minimize the objective.
        num_restarts: L-BFGS-B restarts in ``optimize_acqf``.
        raw_samples: Sobol samples used to pick the restart points.
        seed: base seed of the per-ask RNG.
        options: extra ``options`` for ``optimize_acqf`` (e.g. ``{"maxiter": 200}``).
    """

    name = "bo"

    def __init__(
        self,
        bounds,
        model: Callable[[torch.Tensor, torch.Tensor], Model],
        *,
        acquisition=BO_DEFAULTS["acquisition"],
        beta: float = BO_DEFAULTS["beta"],
        step_limit: float | None = BO_DEFAULTS["step_limit"],
        trust_center: str = BO_DEFAULTS["trust_center"],
        maximize: bool = True,
        num_restarts: int = BO_DEFAULTS["num_restarts"],
        raw_samples: int = BO_DEFAULTS["raw_samples"],
        seed: int = 0,
        options: dict | None = None,
    ) -> None:
        bounds = check_bounds(bounds)
        posterior = BoTorchPosterior(model)
        if isinstance(acquisition, str):
            acq = botorch_analytic(acquisition, beta)
        elif callable(acquisition):  # a BoTorch acquisition used as it is
            acq = BoTorchAcquisition(acquisition)
        else:
            raise ValueError(
                "acquisition must be 'ucb', 'ei', 'logei' or a callable (model, best_f) -> "
                f"botorch AcquisitionFunction, got {acquisition!r}"
            )
        region = TrustRegion(bounds, step_limit, trust_center)
        search = OptimizeAcqf(num_restarts, raw_samples, options)
        super().__init__(bounds, BOParts(posterior, acq, search, region), maximize=maximize,
                         seed=seed)  # fmt: skip
        self.acquisition = acquisition.lower() if isinstance(acquisition, str) else acquisition
        self.beta = float(beta)
        self.trust_center = trust_center
        self.num_restarts, self.raw_samples = search.num_restarts, search.raw_samples
        self.options = search.options
        self.model_factory = model

    @property
    def last_model(self) -> Model | None:
        """The model of the last ask (``None`` before the first)."""
        return self.parts.posterior.model
