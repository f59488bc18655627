r"""A simulated machine: a coupling simulation plus Gaussian measurement noise."""

from __future__ import annotations

import torch

from pigp_torch._utils import DTYPE, as_knob_tensor
from pigp_torch.machine.base import GuardedMachine


class SimulatedMachine(GuardedMachine):
    r"""A simulation behind the :class:`~pigp_torch.machine.base.Machine` interface, with noise.

    A reading at the current knobs :math:`x` is

    .. math:: y = f(x) + \epsilon, \qquad \epsilon \sim \mathcal N(0, \sigma_n^2),

    where :math:`f` is the ``objective`` attribute of ``sim.evaluate(x)`` (by default the loss
    rate in mA/min) and the noise comes from the machine's own seeded ``torch.Generator``, so a run
    is reproducible and does not touch the global RNG.

    Args:
        sim: any object with ``.evaluate(x)`` (``x``: ``d`` or ``N x d``) returning an object whose
            attributes ``eps_x``, ``eps_y``, ``loss_rate`` are tensors, plus ``.bounds``
            (``2 x d``) and ``.knob_names`` — e.g. :class:`pigp_torch.simulation.Spear3Coupling`.
        noise: noise standard deviation :math:`\sigma_n` (objective units; paper: 0.04 mA/min).
        seed: seed of the noise generator.
        objective: name of the attribute of ``sim.evaluate(x)`` that is read.
        max_step: per-knob maximum change per :meth:`set` (scalar fraction of the half-range or
            ``d`` absolute tensor), or ``None``.
        x_init: initial knobs (default zeros: skews off).

    Attributes:
        n_reads: number of noisy readings taken so far.
    """

    def __init__(
        self,
        sim,
        noise: float = 0.04,
        seed: int = 0,
        objective: str = "loss_rate",
        max_step=None,
        x_init=None,
    ) -> None:
        for attr in ("evaluate", "bounds", "knob_names"):
            if not hasattr(sim, attr):
                raise ValueError(f"sim has no attribute {attr!r}")
        super().__init__(sim.bounds, sim.knob_names, max_step=max_step, x_init=x_init)
        noise = float(noise)
        if not (0.0 <= noise < float("inf")):
            raise ValueError(f"noise must be finite and >= 0, got {noise}")
        self.sim = sim
        self.noise = noise
        self.seed = int(seed)
        self.objective = str(objective)
        if not hasattr(sim.evaluate(self._x), self.objective):
            raise ValueError(f"sim.evaluate(x) has no attribute {self.objective!r}")
        self._generator = torch.Generator().manual_seed(self.seed)
        self.n_reads = 0

    def _apply(self, x: torch.Tensor) -> None:
        """Nothing to send: the simulation is evaluated at read time."""

    def true_value(self, x) -> torch.Tensor:
        r"""Noise-free objective :math:`f(x)`: ``N`` tensor for ``N x d`` input, 0-d for ``d``.

        Does not change the knobs, the noise stream or ``n_reads``.
        """
        if not isinstance(x, torch.Tensor):  # lists/arrays straight to float64
            x = torch.as_tensor(x, dtype=DTYPE)
        X, was_1d = as_knob_tensor(x, self.dim)
        with torch.no_grad():
            f = torch.as_tensor(getattr(self.sim.evaluate(X), self.objective), dtype=DTYPE)
        f = f.reshape(-1)
        if f.numel() != X.shape[0]:
            raise ValueError(f"sim returned {f.numel()} values for {X.shape[0]} settings")
        return f[0] if was_1d else f

    def read(self) -> float:
        """One noisy reading at the current knobs."""
        value = float(self.true_value(self._x))
        self.n_reads += 1
        if self.noise > 0:
            eps = torch.randn((), generator=self._generator, dtype=DTYPE)
            value += self.noise * float(eps)
        return value

    def advance_noise(self, n_reads: int) -> None:
        """Move the noise stream on as ``n_reads`` readings would (a resumed run): one normal
        variate per reading, taken through :meth:`read` with the knobs unmoved."""
        if self.noise > 0:
            for _ in range(int(n_reads)):
                self.read()

    def __call__(self, x) -> float:
        """Set the knobs to ``x`` (``d``) and take one reading."""
        self.set(x)
        return self.read()
