r"""A simulated machine made of a machine model: :class:`ModelMachine`.

Any :class:`~pigp_torch.prior.machine_model.MachineModel` at unknowns :math:`\theta^*` the
optimizer is not told is a machine: a reading at the knobs :math:`x` measures the observables
:math:`o = M(x, \theta^*) + \varepsilon` (:math:`\varepsilon \sim N(0, s^2)` on each, ``noise``
:math:`s` in the observables' units) and returns the goal :math:`g(o)` (to minimize), or
:math:`-g(o)` with ``maximize=True``. It keeps the observables of the last reading
(``last_observables``, with ``observable_names`` and ``observable_units``), which the loop logs
and hands to the optimizers that fit them. A machine kind needs no machine class of its own.
"""

from __future__ import annotations

import torch

from pigp_torch._utils import DTYPE, as_knob_tensor
from pigp_torch.machine.base import GuardedMachine


class ModelMachine(GuardedMachine):
    r"""A machine model at true unknowns, read with Gaussian noise (module docstring).

    Args:
        model: the :class:`~pigp_torch.prior.machine_model.MachineModel`.
        theta: ``P`` true unknowns (the model's units).
        noise: standard deviation of each observable's noise (observable units; default 0).
        seed: seed of the noise stream.
        maximize: ``read()`` returns :math:`-g` to be maximized (default ``False``: :math:`g`,
            minimized).
        bounds: ``2 x d`` knob bounds (default the model's).
        max_step: per-knob step limit (:class:`~pigp_torch.machine.base.GuardedMachine`).
        x_init: ``d`` initial setting (default the middle of the bounds).

    Raises:
        ValueError: ``theta`` of the wrong size, or a negative or infinite ``noise``.
    """

    def __init__(
        self,
        model,
        theta,
        *,
        noise: float = 0.0,
        seed: int = 0,
        maximize: bool = False,
        bounds=None,
        max_step=None,
        x_init=None,
    ) -> None:
        bounds = model.bounds if bounds is None else torch.as_tensor(bounds, dtype=DTYPE)
        x0 = (bounds[0] + bounds[1]) / 2 if x_init is None else x_init
        super().__init__(bounds, model.knob_names, max_step=max_step, x_init=x0)
        self.model = model
        self.theta = torch.as_tensor(theta, dtype=DTYPE).reshape(-1)
        if self.theta.numel() != len(model.unknown_names):
            raise ValueError(f"theta needs {len(model.unknown_names)} unknowns")
        if not (0.0 <= float(noise) < float("inf")):
            raise ValueError(f"noise must be finite and >= 0, got {noise}")
        self.noise = float(noise)
        self.maximize = bool(maximize)
        self.knob_units = tuple(model.knob_units)
        self.observable_names = tuple(model.observable_names)
        self.observable_units = tuple(model.observable_units)
        self._generator = torch.Generator().manual_seed(int(seed))
        self.last_observables: torch.Tensor | None = None

    def _apply(self, x: torch.Tensor) -> None:
        """Nothing to send: the model is evaluated at read time."""

    def true_observables(self, x) -> torch.Tensor:
        """Noise-free observables at ``d`` (-> ``m``) or ``N x d`` (-> ``N x m``) settings."""
        X, single = as_knob_tensor(torch.as_tensor(x, dtype=DTYPE), self.dim)
        with torch.no_grad():
            O = self.model.observe(X, self.theta)
        return O[0] if single else O

    def value_of(self, observables: torch.Tensor) -> torch.Tensor:
        """``read()``'s value of observables: the goal, negated when maximized."""
        g = self.model.goal(torch.as_tensor(observables, dtype=DTYPE))
        return -g if self.maximize else g

    def read_observables(self) -> torch.Tensor:
        """One noisy reading of the ``m`` observables at the current knobs (kept in
        :attr:`last_observables`)."""
        o = self.true_observables(self._x)
        if self.noise > 0:
            o = o + self.noise * torch.randn(o.shape, generator=self._generator, dtype=DTYPE)
        self.last_observables = o
        return o.clone()

    def read(self) -> float:
        """One reading: the value of :meth:`read_observables`."""
        return float(self.value_of(self.read_observables()[None])[0])

    def advance_noise(self, n_reads: int) -> None:
        """Move the noise stream on as ``n_reads`` readings would (a resumed run)."""
        if self.noise > 0:
            for _ in range(int(n_reads)):
                self.read_observables()
