r"""An operating-point archive of a simulated machine, for the data-informed baseline (ML-II).

The benchmark's ``ml2`` fits its hyperparameters first on readings of the machine near skews-off
(an archive a control room could have); :func:`machine_archive` draws them from the simulated
machine's noise-free value plus noise, so it lives with the benchmark, not with the methods: the
protocol hands it to the builders as :attr:`RunContext.archive
<pigp_torch.methods.registry.RunContext>`.
"""

from __future__ import annotations

import torch

from pigp_torch._utils import DTYPE


def machine_archive(
    machine, size: int, *, spread: float = 0.2, seed: int = 0
) -> tuple[torch.Tensor, torch.Tensor]:
    r"""``size`` noisy readings of a simulated ``machine`` near skews-off (an operating-point
    archive).

    Settings :math:`x_i \sim \mathcal N(0, (s\,h)^2)` per knob (:math:`h` the half-range,
    :math:`s` = ``spread``) clipped to the bounds; readings :math:`f(x_i) + \epsilon_i`,
    :math:`\epsilon_i \sim \mathcal N(0, \sigma_n^2)` with the machine's noise level, drawn from a
    generator seeded by ``seed`` (the machine's own noise stream is not touched). ``machine``
    needs ``bounds``, ``dim``, ``noise`` and ``true_value`` (a
    :class:`~pigp_torch.machine.SimulatedMachine`).

    Returns:
        ``(X_a: size x d, Y_a: size)``.
    """
    if int(size) < 1:
        raise ValueError(f"archive size must be >= 1, got {size}")
    gen = torch.Generator().manual_seed(int(seed))
    lower, upper = machine.bounds
    center, half = (upper + lower) / 2, (upper - lower) / 2
    Z = torch.randn(int(size), machine.dim, generator=gen, dtype=DTYPE)
    X = torch.minimum(torch.maximum(center + spread * half * Z, lower), upper)
    eps = torch.randn(int(size), generator=gen, dtype=DTYPE)
    return X, machine.true_value(X) + machine.noise * eps
