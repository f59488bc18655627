"""Every machine kind passes the contract shipped in :mod:`pigp_torch.machines.contract`."""

from __future__ import annotations

from typing import ClassVar

from pigp_torch.machines.contract import MachineKindContract


class TestAresKind(MachineKindContract):
    kind_name = "ares-ea"
    model_options: ClassVar[dict] = {"trial": 3}
    noise = 5e-6  # m, a screen's noise on the MAE goal
    prior_options: ClassVar[dict] = {"n_starts": 1, "n_samples": 16}  # Cheetah: the slow part


class TestRingKind(MachineKindContract):
    kind_name = "spear3"
    model_options: ClassVar[dict] = {"error_seed": 0}
    noise = 0.04  # mA/min, the benchmark's reading noise
