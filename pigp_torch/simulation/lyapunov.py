"""Alias: the ring's lyapunov module moved to the ring machine kind's folder,
:mod:`pigp_torch.machines.ring.lyapunov`; this module keeps the old import path working."""

from pigp_torch.machines.ring.lyapunov import (
    J6,
    eigen_emittances,
    lyapunov_doubling,
)

__all__ = [
    "J6",
    "eigen_emittances",
    "lyapunov_doubling",
]
