r"""Simulated-data files: one NPZ per dataset, arrays plus JSON metadata, loaded without pickle.

Layout (all float64):

* ``x``: ``N x d`` knob settings (control units: amps of the skew windings for SPEAR3),
* ``loss_rate``: ``N`` Touschek loss-rate proxy (mA/min),
* ``eps_x``, ``eps_y``: ``N`` mode emittances (m rad),
* ``metadata``: a 0-d unicode array holding a JSON object (error seed, knob names, bounds, units,
  background loss rate ``f_inf``, package version, sampling design).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

ARRAYS = ("x", "loss_rate", "eps_x", "eps_y")


@dataclass
class Dataset:
    """Samples of the coupling simulation with their provenance."""

    x: torch.Tensor
    loss_rate: torch.Tensor
    eps_x: torch.Tensor
    eps_y: torch.Tensor
    metadata: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        n = self.x.shape[0]
        if self.x.dim() != 2:
            raise ValueError(f"x must be N x d, got shape {tuple(self.x.shape)}")
        for name in ARRAYS[1:]:
            a = getattr(self, name)
            if a.shape != (n,):
                raise ValueError(f"{name} must have shape ({n},), got {tuple(a.shape)}")

    def __len__(self) -> int:
        return self.x.shape[0]

    @property
    def knob_names(self) -> list[str]:
        return list(self.metadata.get("knob_names", []))

    @property
    def bounds(self) -> torch.Tensor:
        return torch.tensor(self.metadata["bounds"], dtype=torch.float64)

    @property
    def f_inf(self) -> float:
        return float(self.metadata["f_inf"])

    def save(self, path: str | Path) -> Path:
        """Write the dataset as a compressed NPZ; returns the path written."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        arrays = {k: getattr(self, k).detach().cpu().numpy() for k in ARRAYS}
        with open(path, "wb") as fh:
            np.savez_compressed(fh, metadata=np.array(json.dumps(self.metadata)), **arrays)
        return path

    @classmethod
    def load(cls, path: str | Path) -> Dataset:
        """Read a dataset written by :meth:`save` (no pickle is ever loaded)."""
        path = Path(path)
        if not path.exists():
            raise FileNotFoundError(f"dataset file not found: {path}")
        with np.load(path, allow_pickle=False) as z:
            missing = [k for k in (*ARRAYS, "metadata") if k not in z.files]
            if missing:
                raise ValueError(f"{path} is not a pigp dataset: missing arrays {missing}")
            arrays = {k: torch.from_numpy(np.asarray(z[k], dtype=np.float64)) for k in ARRAYS}
            metadata = json.loads(str(z["metadata"]))
        return cls(metadata=metadata, **arrays)
