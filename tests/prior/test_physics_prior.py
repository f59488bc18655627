"""Tests of the PhysicsPrior data class: validation, derived quantities, JSON round trip."""

import json

import pytest
import torch

from pigp_torch.prior import PhysicsPrior


def _prior(**overrides):
    P = torch.tensor(
        [[4.0e4, 1.0e4, 0.0], [1.0e4, 2.0e4, 5.0e3], [0.0, 5.0e3, 1.0e4]], dtype=torch.float64
    )
    kwargs = dict(
        x0=torch.tensor([0.001, -0.002, 0.003], dtype=torch.float64),
        f_x0=1.7,
        f_inf=0.2,
        precision=P,
        amplitude=1.5**2 / 12,
        noise=0.04,
        knob_names=["01G-QSS4", "02G-QSS3", "03G-QSS3"],
        bounds=torch.tensor([[-0.015, -0.01, -0.02], [0.015, 0.01, 0.02]], dtype=torch.float64),
        gradient=torch.tensor([1e-9, 0.0, -2e-9], dtype=torch.float64),
        provenance={"surrogate": "mlp.pt", "seed": 3, "nested": {"a": [1, 2.5]}},
    )
    kwargs.update(overrides)
    return PhysicsPrior(**kwargs)


def test_fields_are_float64_tensors_and_floats():
    """Tensor fields are converted to float64, scalar fields to Python floats."""
    p = _prior()
    for t in (p.x0, p.precision, p.bounds, p.gradient):
        assert t.dtype == torch.float64
    assert isinstance(p.f_x0, float) and isinstance(p.noise, float)
    assert p.dim == 3


def test_save_load_round_trip_is_exact(tmp_path):
    """save then load reproduces every field bit for bit (plain JSON file)."""
    g = torch.Generator().manual_seed(0)
    A = torch.randn(3, 3, generator=g, dtype=torch.float64)
    p = _prior(precision=A @ A.T + 3 * torch.eye(3), x0=torch.randn(3, generator=g) * 1e-3)
    path = tmp_path / "prior.json"
    p.save(path)
    data = json.loads(path.read_text())
    assert data["format"] == "pigp_torch.PhysicsPrior"
    q = PhysicsPrior.load(path)
    for name in ("x0", "precision", "bounds", "gradient"):
        assert torch.equal(getattr(p, name), getattr(q, name)), name
    for name in ("f_x0", "f_inf", "amplitude", "noise", "knob_names", "provenance"):
        assert getattr(p, name) == getattr(q, name), name


def test_ensemble_fields_round_trip_and_absence(tmp_path):
    """An ensemble ``center_cov`` and ``peak_shape`` are saved and loaded bit for bit; a prior
    without them writes no such keys and loads with ``None`` (files from before the fields still
    load)."""
    g = torch.Generator().manual_seed(1)
    A = torch.randn(5, 3, generator=g, dtype=torch.float64) * 1e-2
    C = A.T @ A / 5
    p = _prior(center_cov=C, peak_shape=torch.linalg.inv(C) * 7.0)
    p.save(tmp_path / "with.json")
    q = PhysicsPrior.load(tmp_path / "with.json")
    for name in ("center_cov", "peak_shape"):
        assert torch.equal(getattr(q, name), getattr(p, name)), name
        assert getattr(q, name).dtype == torch.float64
    _prior().save(tmp_path / "without.json")
    record = json.loads((tmp_path / "without.json").read_text())
    assert "center_cov" not in record and "peak_shape" not in record
    loaded = PhysicsPrior.load(tmp_path / "without.json")
    assert loaded.center_cov is None and loaded.peak_shape is None


def test_load_rejects_foreign_json(tmp_path):
    """A JSON file without the PhysicsPrior format tag, or with broken JSON, raises ValueError."""
    path = tmp_path / "x.json"
    path.write_text(json.dumps({"x0": [0.0]}))
    with pytest.raises(ValueError, match="format tag"):
        PhysicsPrior.load(path)
    path.write_text("{not json")
    with pytest.raises(ValueError, match="not valid JSON"):
        PhysicsPrior.load(path)


def test_normalized_precision_closed_form():
    """S P S with S = diag(half-ranges); q is the same in raw and normalized coordinates."""
    p = _prior()
    s = torch.tensor([0.015, 0.01, 0.02], dtype=torch.float64)
    Pu = p.normalized_precision()
    for i in range(3):
        for j in range(3):
            assert Pu[i, j].item() == pytest.approx(
                (p.precision[i, j] * s[i] * s[j]).item(), rel=1e-14
            )
    u = torch.tensor([0.3, -0.7, 0.2], dtype=torch.float64)
    dx = s * u  # the same displacement in knob units
    assert (u @ Pu @ u).item() == pytest.approx((dx @ p.precision @ dx).item(), rel=1e-13)


def test_length_scales_of_diagonal_precision():
    """For P = diag(1/l^2) the lengths are l sorted ascending with unit-vector directions."""
    ls = torch.tensor([0.01, 0.002, 0.005], dtype=torch.float64)
    p = _prior(precision=torch.diag(ls**-2))
    lengths, dirs = p.length_scales()
    torch.testing.assert_close(
        lengths, torch.tensor([0.002, 0.005, 0.01], dtype=torch.float64), rtol=1e-12, atol=0
    )
    torch.testing.assert_close(dirs.abs(), torch.eye(3)[:, [1, 2, 0]].double(), rtol=0, atol=1e-12)
    # normalized: in units of the half-ranges (0.015, 0.01, 0.02)
    ln, _ = p.length_scales(normalized=True)
    expected = torch.sort(ls / torch.tensor([0.015, 0.01, 0.02], dtype=torch.float64)).values
    torch.testing.assert_close(ln, expected, rtol=1e-12, atol=0)


def test_correlation_matrix_of_covariance_and_precision():
    """The covariance correlation is that of P^-1; the precision one is P normalized."""
    C = torch.tensor([[4.0, 1.2, 0.0], [1.2, 1.0, -0.3], [0.0, -0.3, 2.25]], dtype=torch.float64)
    p = _prior(precision=torch.linalg.inv(C))
    R = p.correlation_matrix()
    assert R[0, 1].item() == pytest.approx(1.2 / (2.0 * 1.0), rel=1e-12)
    assert R[1, 2].item() == pytest.approx(-0.3 / (1.0 * 1.5), rel=1e-12)
    assert R[0, 2].item() == pytest.approx(0.0, abs=1e-14)
    torch.testing.assert_close(R.diagonal(), torch.ones(3, dtype=torch.float64))
    Rp = p.correlation_matrix(of="precision")
    P = p.precision
    assert Rp[0, 1].item() == pytest.approx(
        (P[0, 1] / (P[0, 0] * P[1, 1]).sqrt()).item(), rel=1e-12
    )
    with pytest.raises(ValueError, match="covariance"):
        p.correlation_matrix(of="hessian")


def test_condition_number():
    """condition_number is the eigenvalue ratio of the precision."""
    p = _prior(precision=torch.diag(torch.tensor([1.0, 483.0, 20.0])))
    assert p.condition_number == pytest.approx(483.0, rel=1e-12)


def test_gradient_defaults_to_zero():
    """Without a gradient the prior stores zeros of the right size."""
    p = _prior(gradient=None)
    assert torch.equal(p.gradient, torch.zeros(3, dtype=torch.float64))


@pytest.mark.parametrize(
    ("overrides", "match"),
    [
        ({"x0": torch.zeros(2)}, "x0 must have shape"),
        ({"x0": torch.tensor([0.0, float("nan"), 0.0])}, "x0 contains NaN"),
        ({"precision": torch.eye(2)}, "precision must have shape"),
        ({"precision": torch.tensor([[1.0, 2, 0], [2, 1, 0], [0, 0, 1]])}, "positive definite"),
        ({"precision": torch.tensor([[1.0, 0.1, 0], [0, 1, 0], [0, 0, 1]])}, "symmetric"),
        ({"f_inf": 1.7}, "f_inf"),
        ({"f_x0": float("inf")}, "f_x0 must be finite"),
        ({"amplitude": 0.0}, "amplitude"),
        ({"noise": -0.01}, "noise"),
        ({"knob_names": ["a", "b"]}, "x0 must have shape"),
        ({"knob_names": ["a", "a", "b"]}, "unique"),
        ({"knob_names": "abc"}, "list of strings"),
        ({"bounds": torch.tensor([[0.1, 0.0, 0.0], [0.0, 1.0, 1.0]])}, "lower bound"),
        ({"bounds": torch.zeros(3, 3)}, "bounds must have shape"),
        ({"gradient": torch.zeros(4)}, "gradient must have shape"),
        ({"center_cov": torch.eye(2)}, "center_cov must have shape"),
        ({"center_cov": torch.diag(torch.tensor([1.0, 0.0, 1.0]))}, "center_cov must be positive"),
        ({"center_cov": torch.tensor([[1.0, 0.1, 0], [0, 1, 0], [0, 0, 1]])}, "center_cov must be"),
        ({"peak_shape": torch.eye(4)}, "peak_shape must have shape"),
        ({"peak_shape": -torch.eye(3)}, "peak_shape must be positive"),
        ({"provenance": {"bad": object()}}, "JSON"),
        ({"provenance": {"bad": float("nan")}}, "JSON"),
    ],
)
def test_validation_errors(overrides, match):
    """Each invalid field raises ValueError naming the problem."""
    with pytest.raises(ValueError, match=match):
        _prior(**overrides)
