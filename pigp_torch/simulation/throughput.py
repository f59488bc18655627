"""Alias: the ring's throughput module moved to the ring machine kind's folder,
:mod:`pigp_torch.machines.ring.throughput`; this module keeps the old import path working."""

from pigp_torch.machines.ring.throughput import (
    gpu_status,
    measure_throughput,
)

__all__ = [
    "gpu_status",
    "measure_throughput",
]
