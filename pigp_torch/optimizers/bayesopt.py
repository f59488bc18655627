r"""Bayesian optimization as an ask/tell optimizer, with a trust box around the best point.

Each :meth:`BayesOpt.ask` builds a GP from all measurements so far (through a user-given model
factory, e.g. the physics-informed GP whose kernel is fixed in advance), then maximizes an
acquisition function inside a *trust box*: the knob bounds intersected with a box of half-width
``step_limit`` (in normalized knob units) around a center point. The step limit is part of the
method (a fixed-kernel UCB without it wanders to the corners of a 13-D box) and a safety rule on a
real machine.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import torch
from botorch.acquisition import (
    AcquisitionFunction,
    ExpectedImprovement,
    LogExpectedImprovement,
    UpperConfidenceBound,
)
from botorch.models.model import Model
from botorch.optim import optimize_acqf

from pigp_torch._utils import DTYPE
from pigp_torch.optimizers.base import (
    AskTellOptimizer,
    check_search_options,
    check_ucb_options,
    trust_box,
)

ACQUISITIONS = ("ucb", "ei", "logei")
TRUST_CENTERS = ("best_observed", "best_mean")


class _BoxAcquisition(AcquisitionFunction):
    r"""An acquisition function seen through the affine map of the unit cube onto a box.

    .. math:: \tilde a(u) = a(\ell + u \odot (h - \ell)), \qquad u \in [0, 1]^d

    Optimizing over the unit cube keeps L-BFGS-B well conditioned whatever the knob units.
    """

    def __init__(self, acq: AcquisitionFunction, lower: torch.Tensor, upper: torch.Tensor):
        super().__init__(model=acq.model)
        self.acq = acq
        self.register_buffer("lower", lower)
        self.register_buffer("width", upper - lower)

    def forward(self, U: torch.Tensor) -> torch.Tensor:
        return self.acq(self.lower + U * self.width)


class BayesOpt(AskTellOptimizer):
    r"""GP Bayesian optimization with UCB / EI acquisition restricted to a trust box.

    **Model.** ``model(X, Y)`` is called at every :meth:`ask` with all data told so far,
    ``X: n x d`` and ``Y: n x 1`` (float64), and must return a BoTorch ``Model``. Internally the
    optimizer always *maximizes*: with ``maximize=False`` it passes ``Y = -y`` to the factory, so
    the model sees the negated objective (a prior mean in the factory must then be negated too).

    **Acquisition** (on the internal, maximized objective, posterior mean :math:`\mu`, standard
    deviation :math:`\sigma`, best observed value :math:`y^*`):

    * ``"ucb"``: :math:`\mu(x) + \sqrt{\beta}\,\sigma(x)` (BoTorch convention; ``beta=4`` is the
      authors' :math:`\mu + 2\sigma`);
    * ``"ei"``: :math:`E[\max(g(x) - y^*, 0)]`; ``"logei"``: its numerically robust logarithm.

    **Trust box.** With :math:`c` the center, :math:`\ell, h` the knob bounds and
    :math:`s` = ``step_limit``, the candidate is searched in

    .. math:: \max\!\big(\ell,\; c - s\,\tfrac{h - \ell}{2}\big) \le x \le
              \min\!\big(h,\; c + s\,\tfrac{h - \ell}{2}\big)

    i.e. with knobs normalized to :math:`[-1, 1]` the box is :math:`c \pm s` per knob. The center
    is chosen among the told points (clamped into the bounds, so points told from outside them
    cannot empty the box):

    * ``"best_observed"``: the point with the best noisy reading (first one on ties);
    * ``"best_mean"``: the point with the highest posterior mean of the current model, which a
      single lucky noisy reading cannot capture.

    ``step_limit=None`` searches the whole knob box. The result of ``optimize_acqf`` is clamped
    into the trust box as a final guard, so a proposal never leaves the bounds or the box.

    **Determinism.** Each ask seeds a forked torch RNG with ``seed + n_told``; the global RNG
    state is left untouched.

    After each ask, ``last_info`` holds ``acq_value``, ``center`` (``d``), ``trust_lower`` and
    ``trust_upper`` (``d``), ``fit_time_s`` (model factory), ``acq_time_s`` (acquisition
    optimization) and ``n_train``; ``last_model`` holds the model.

    Args:
        bounds: ``2 x d`` knob bounds.
        model: factory ``(X: n x d, Y: n x 1) -> Model``.
        acquisition: ``"ucb"``, ``"ei"`` or ``"logei"``.
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
        acquisition: str = "ucb",
        beta: float = 4.0,
        step_limit: float | None = 0.1,
        trust_center: str = "best_observed",
        maximize: bool = True,
        num_restarts: int = 10,
        raw_samples: int = 256,
        seed: int = 0,
        options: dict | None = None,
    ) -> None:
        super().__init__(bounds, maximize=maximize)
        if not callable(model):
            raise ValueError("model must be a callable (X: n x d, Y: n x 1) -> botorch Model")
        acquisition = str(acquisition).lower()
        if acquisition not in ACQUISITIONS:
            raise ValueError(f"acquisition must be one of {ACQUISITIONS}, got {acquisition!r}")
        check_ucb_options(beta, step_limit)
        check_search_options(trust_center, TRUST_CENTERS, num_restarts, raw_samples)
        self.model_factory = model
        self.acquisition = acquisition
        self.beta = float(beta)
        self.step_limit = None if step_limit is None else float(step_limit)
        self.trust_center = trust_center
        self.num_restarts = int(num_restarts)
        self.raw_samples = int(raw_samples)
        self.seed = int(seed)
        self.options = dict(options or {})
        self.last_info: dict = {}
        self.last_model: Model | None = None

    # -- data in the internal (maximized) sign -------------------------------------------------
    def train_data(self) -> tuple[torch.Tensor, torch.Tensor]:
        r"""All told data as ``(X: n x d, Y: n x 1)``, ``Y`` negated when minimizing."""
        if not self.Y:
            raise RuntimeError("no measurements yet: tell() the start point first")
        X = torch.stack(self.X)
        Y = torch.tensor(self.Y, dtype=DTYPE).unsqueeze(-1)
        return X, (Y if self.maximize else -Y)

    def trust_box(self, center: torch.Tensor) -> torch.Tensor:
        r"""The ``2 x d`` search box around ``center`` (``d``), see the class docstring."""
        return trust_box(self.bounds, center, self.step_limit)

    def _center(self, model: Model, X: torch.Tensor, Y: torch.Tensor) -> torch.Tensor:
        if self.trust_center == "best_observed":
            return X[int(Y.squeeze(-1).argmax())]
        with torch.no_grad():
            mean = model.posterior(X).mean.reshape(-1)
        return X[int(mean.argmax())]

    def _acquisition_function(self, model: Model, Y: torch.Tensor) -> AcquisitionFunction:
        if self.acquisition == "ucb":
            return UpperConfidenceBound(model, beta=self.beta)
        best_f = Y.max()
        if self.acquisition == "ei":
            return ExpectedImprovement(model, best_f=best_f)
        return LogExpectedImprovement(model, best_f=best_f)

    def ask(self) -> torch.Tensor:
        r"""Fit the model to all data, maximize the acquisition in the trust box; returns ``d``."""
        X, Y = self.train_data()
        with torch.random.fork_rng():
            torch.manual_seed(self.seed + self.n_told)
            t0 = time.perf_counter()
            model = self.model_factory(X, Y)
            if not isinstance(model, Model):
                raise ValueError(f"model factory returned {type(model).__name__}, not a Model")
            t1 = time.perf_counter()
            center = self._center(model, X, Y)
            box = self.trust_box(center)
            acq = _BoxAcquisition(self._acquisition_function(model, Y), box[0], box[1])
            unit = torch.stack(
                [torch.zeros(self.dim, dtype=DTYPE), torch.ones(self.dim, dtype=DTYPE)]
            )
            u, value = optimize_acqf(
                acq,
                bounds=unit,
                q=1,
                num_restarts=self.num_restarts,
                raw_samples=self.raw_samples,
                options=self.options,
            )
            t2 = time.perf_counter()
        x = box[0] + u.detach().reshape(-1).clamp(0.0, 1.0) * (box[1] - box[0])
        x = torch.minimum(torch.maximum(x, box[0]), box[1])  # final guard against round-off
        self.last_model = model
        self.last_info = {
            "acq_value": float(value.detach().reshape(-1)[0]),
            "center": center.clone(),
            "trust_lower": box[0].clone(),
            "trust_upper": box[1].clone(),
            "fit_time_s": t1 - t0,
            "acq_time_s": t2 - t1,
            "n_train": X.shape[0],
        }
        return x
