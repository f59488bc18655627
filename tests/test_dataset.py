"""Dataset files: exact round trip, no pickle, clear errors."""

import numpy as np
import pytest
import torch

from pigp_torch.data.dataset import Dataset


def make(n=5, d=3):
    g = torch.Generator().manual_seed(0)
    x = torch.rand(n, d, generator=g, dtype=torch.float64)
    v = torch.rand(n, generator=g, dtype=torch.float64)
    return Dataset(x=x, loss_rate=v, eps_x=v * 2, eps_y=v * 3, metadata={"f_inf": 0.1, "a": [1]})


def test_round_trip(tmp_path):
    """Saved arrays and metadata load back bit for bit."""
    ds = make()
    back = Dataset.load(ds.save(tmp_path / "x.npz"))
    for k in ("x", "loss_rate", "eps_x", "eps_y"):
        assert torch.equal(getattr(back, k), getattr(ds, k))
    assert back.metadata == ds.metadata and back.f_inf == 0.1


def test_object_arrays_are_refused(tmp_path):
    """A file holding a pickled object array cannot be loaded (allow_pickle=False)."""
    path = tmp_path / "evil.npz"
    np.savez(path, x=np.zeros((1, 2)), loss_rate=np.zeros(1), eps_x=np.zeros(1),
             eps_y=np.zeros(1), metadata=np.array([{"a": 1}], dtype=object))  # fmt: skip
    with pytest.raises(ValueError):
        Dataset.load(path)


def test_errors(tmp_path):
    """Missing files, foreign files and inconsistent shapes raise clear errors."""
    with pytest.raises(FileNotFoundError):
        Dataset.load(tmp_path / "none.npz")
    np.savez(tmp_path / "other.npz", a=np.zeros(2))
    with pytest.raises(ValueError, match="not a pigp dataset"):
        Dataset.load(tmp_path / "other.npz")
    with pytest.raises(ValueError, match="shape"):
        Dataset(x=torch.zeros(3, 2), loss_rate=torch.zeros(2), eps_x=torch.zeros(3),
                eps_y=torch.zeros(3))  # fmt: skip
