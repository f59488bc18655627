r"""The published Bayesian-optimisation recipe of the ARES-EA tuning task, as an ask/tell optimizer.

Reproduced from its description (BoTorch parts, no hand-written GP):

* knobs scaled to :math:`[-s, s]` (:math:`s = 3`) over the bounds (the published run used
  unidirectional quadrupoles), :math:`z = s\,(2 (x - \ell)/(h - \ell) - 1)`;
* the first sample is the start :math:`x_0`; the next ``n_init`` (4) are uniform in the box
  :math:`z_0 \pm b` (:math:`b = 0.3`, a box 10 % as wide as the range) clipped to :math:`[-s, s]`;
* then each step: a :class:`~botorch.models.SingleTaskGP` on the scaled knobs with a
  standardised outcome, its hyperparameters fitted by ML-II (:func:`~botorch.fit.fit_gpytorch_mll`);
  Expected Improvement with ``best_f`` the best value so far (:class:`~botorch.acquisition.
  analytic.ExpectedImprovement`, or its log form with ``log_ei=True``), maximized by
  :func:`~botorch.optim.optimize_acqf` (10 restarts, 256 raw samples, 200 iterations) inside the
  box :math:`\pm b` around the LAST sample (clipped to :math:`[-s, s]`).

Setting the knobs back to the best sample at the end is the caller's part (:meth:`best`).
"""

from __future__ import annotations

import warnings

import torch

from pigp_torch._utils import DTYPE
from pigp_torch.optimizers.base import AskTellOptimizer


class PublishedAresBO(AskTellOptimizer):
    r"""EI Bayesian optimisation in a moving box, as published for ARES-EA (module docstring).

    Args:
        bounds: ``2 x d`` knob bounds (physical units).
        x0: ``d`` start setting (physical units; clipped to the bounds).
        n_init: random samples after the start (default 4).
        box: half width of the sampling / search box on the scaled knobs (default 0.3).
        scale: the scaled knobs span :math:`[-s, s]` (default 3).
        num_restarts, raw_samples, maxiter: :func:`optimize_acqf` settings (10, 256, 200).
        log_ei: use LogExpectedImprovement (numerically safer; default ``False``: EI as published).
        seed: seed of the random samples and of the acquisition's raw samples.
        maximize: maximize (default) or minimize the objective.
    """

    name = "published-bo"

    def __init__(
        self,
        bounds,
        *,
        x0,
        n_init: int = 4,
        box: float = 0.3,
        scale: float = 3.0,
        num_restarts: int = 10,
        raw_samples: int = 256,
        maxiter: int = 200,
        log_ei: bool = False,
        seed: int = 0,
        maximize: bool = True,
    ) -> None:
        super().__init__(bounds, maximize=maximize)
        x0 = self._check_point(x0)
        self.x0 = torch.minimum(torch.maximum(x0, self.bounds[0]), self.bounds[1])
        if int(n_init) < 0 or not (0 < float(box) <= float(scale)):
            raise ValueError("n_init must be >= 0 and 0 < box <= scale")
        self.n_init = int(n_init)
        self.box = float(box)
        self.scale = float(scale)
        self.num_restarts = int(num_restarts)
        self.raw_samples = int(raw_samples)
        self.maxiter = int(maxiter)
        self.log_ei = bool(log_ei)
        self.seed = int(seed)
        self._gen = torch.Generator().manual_seed(self.seed)

    def to_scaled(self, x: torch.Tensor) -> torch.Tensor:
        """Physical knobs ``... x d`` -> scaled ``[-s, s]``."""
        lo, hi = self.bounds
        return self.scale * (2 * (x - lo) / (hi - lo) - 1)

    def from_scaled(self, z: torch.Tensor) -> torch.Tensor:
        """Scaled knobs ``... x d`` -> physical units (clipped to the bounds against round-off)."""
        lo, hi = self.bounds
        x = lo + (z / self.scale + 1) / 2 * (hi - lo)
        return torch.minimum(torch.maximum(x, lo), hi)

    def _box(self, center_z: torch.Tensor) -> torch.Tensor:
        s = self.scale
        return torch.stack([(center_z - self.box).clamp(-s, s), (center_z + self.box).clamp(-s, s)])

    def ask(self) -> torch.Tensor:
        """The next setting (``d``, physical units)."""
        n = self.n_told
        if n == 0:
            return self.x0.clone()
        if n <= self.n_init:
            b = self._box(self.to_scaled(self.X[0]))
            u = torch.rand(self.dim, generator=self._gen, dtype=DTYPE)
            return self.from_scaled(b[0] + u * (b[1] - b[0]))
        return self.from_scaled(self._acquire())

    def _acquire(self) -> torch.Tensor:
        from botorch.acquisition.analytic import ExpectedImprovement, LogExpectedImprovement
        from botorch.fit import fit_gpytorch_mll
        from botorch.models import SingleTaskGP
        from botorch.models.transforms.outcome import Standardize
        from botorch.optim import optimize_acqf
        from gpytorch.mlls import ExactMarginalLogLikelihood

        Z = self.to_scaled(torch.stack(self.X))
        sign = 1.0 if self.maximize else -1.0
        Y = sign * torch.tensor(self.Y, dtype=DTYPE).unsqueeze(-1)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # input-range and EI-numerics advice of BoTorch
            gp = SingleTaskGP(Z, Y, outcome_transform=Standardize(m=1))
            fit_gpytorch_mll(ExactMarginalLogLikelihood(gp.likelihood, gp))
            acq_cls = LogExpectedImprovement if self.log_ei else ExpectedImprovement
            acq = acq_cls(gp, best_f=Y.max())
            cand, _ = optimize_acqf(
                acq,
                bounds=self._box(Z[-1]),
                q=1,
                num_restarts=self.num_restarts,
                raw_samples=self.raw_samples,
                options={"maxiter": self.maxiter, "seed": self.seed * 100_003 + self.n_told},
            )
        return cand.detach().reshape(-1)
