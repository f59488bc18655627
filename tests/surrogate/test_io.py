"""Tests of pickle-free saving and loading of surrogates."""

from __future__ import annotations

import json

import pytest
import torch

from pigp_torch.surrogate import SurrogateMLP, load_surrogate, save_surrogate
from pigp_torch.surrogate.io import FORMAT, FORMAT_VERSION

BOUNDS = torch.tensor([[-0.015] * 4, [0.015] * 4], dtype=torch.float64)
_UNPICKLED = []


def _record_call():
    _UNPICKLED.append(True)
    return "payload"


class _CodeOnLoad:
    """Object whose unpickling would call a function (what weights_only must prevent)."""

    def __reduce__(self):
        return (_record_call, ())


def _model(target="log_excess"):
    torch.manual_seed(3)
    return SurrogateMLP(
        BOUNDS,
        0.21,
        widths=(16, 8),
        activation="tanh",
        target=target,
        target_mean=-0.4,
        target_std=0.8,
    )


@pytest.mark.parametrize("target", ["log_excess", "inv_sq_excess", "raw"])
def test_round_trip_identical_outputs(tmp_path, target):
    """A saved and reloaded model gives bit-identical outputs (float64) and the same metadata."""
    m = _model(target).double().eval()
    meta = {"knob_names": ["a", "b", "c", "d"], "metrics": {"r2": 0.99}, "seed": 1}
    path = save_surrogate(m, tmp_path / "sub" / "m.pt", meta)
    m2, meta2 = load_surrogate(path)
    x = 0.015 * (2 * torch.rand(50, 4, dtype=torch.float64) - 1)
    assert torch.equal(m(x), m2(x))
    assert torch.equal(m.log_excess(x), m2.log_excess(x))
    assert meta2 == meta
    assert m2.config == m.config
    assert m2.f_inf.dtype == torch.float64 and m2.net[0].weight.dtype == torch.float64
    assert not m2.training


def test_float32_model_saved_as_float64(tmp_path):
    """A float32 model is stored in float64; reloaded outputs equal the float32 model's to 1e-6."""
    m = _model().eval()
    m2, _ = load_surrogate(save_surrogate(m, tmp_path / "m.pt", {}))
    x = 0.01 * torch.rand(10, 4, dtype=torch.float64)
    assert m2.f_inf.dtype == torch.float64
    torch.testing.assert_close(m2(x), m(x).double(), rtol=1e-6, atol=1e-7)


def test_load_refuses_pickled_objects(tmp_path):
    """A file holding an arbitrary Python object is refused (weights_only=True) with ValueError."""
    path = tmp_path / "evil.pt"
    good = torch.load(save_surrogate(_model(), tmp_path / "g.pt", {}), weights_only=True)
    good["metadata"] = _CodeOnLoad()
    torch.save(good, path)
    with pytest.raises(ValueError, match="weights_only"):
        load_surrogate(path)
    assert _UNPICKLED == []  # the function was never called
    assert torch.load(path, weights_only=False)["metadata"] == "payload"  # the trap is real
    assert _UNPICKLED == [True]


def test_load_rejects_missing_keys_and_bad_files(tmp_path):
    """Missing keys, a wrong format tag or mismatched weights raise ValueError."""
    base = torch.load(save_surrogate(_model(), tmp_path / "g.pt", {}), weights_only=True)
    for key in ("config", "state_dict", "metadata", "format"):
        bad = {k: v for k, v in base.items() if k != key}
        torch.save(bad, tmp_path / "bad.pt")
        with pytest.raises(ValueError, match="missing keys"):
            load_surrogate(tmp_path / "bad.pt")
    torch.save({**base, "format": "other"}, tmp_path / "bad.pt")
    with pytest.raises(ValueError, match="format"):
        load_surrogate(tmp_path / "bad.pt")
    cfg = json.loads(base["config"])
    torch.save({**base, "config": json.dumps({**cfg, "widths": [16, 9]})}, tmp_path / "bad.pt")
    with pytest.raises(ValueError, match="architecture"):
        load_surrogate(tmp_path / "bad.pt")
    torch.save([1, 2], tmp_path / "bad.pt")
    with pytest.raises(ValueError, match="not a dict"):
        load_surrogate(tmp_path / "bad.pt")
    with pytest.raises(FileNotFoundError):
        load_surrogate(tmp_path / "none.pt")
    assert base["format"] == FORMAT and base["format_version"] == FORMAT_VERSION


def test_save_rejects_bad_metadata(tmp_path):
    """Metadata that JSON cannot encode, or a non-surrogate model, raise ValueError."""
    with pytest.raises(ValueError, match="JSON"):
        save_surrogate(_model(), tmp_path / "m.pt", {"x": torch.zeros(2)})
    with pytest.raises(ValueError, match="SurrogateMLP"):
        save_surrogate(torch.nn.Linear(2, 1), tmp_path / "m.pt", {})
