"""Tests of the smooth surrogate MLP: normalizations, target transforms, differentiability."""

from __future__ import annotations

import math

import pytest
import torch

from pigp_torch.surrogate import SurrogateMLP

BOUNDS = torch.tensor([[-0.01, -0.02, 0.0], [0.03, 0.02, 0.5]], dtype=torch.float64)


def _model(target="log_excess", activation="silu", **kw):
    torch.manual_seed(0)
    return SurrogateMLP(
        BOUNDS, 0.2, widths=(8, 8), activation=activation, target=target, **kw
    ).double()


@pytest.mark.parametrize("act", ["relu", "ReLU", "leaky_relu", "elu"])
def test_relu_type_activation_rejected(act):
    """A piecewise-linear (or non-C2) activation is refused because its Hessian is useless."""
    with pytest.raises(ValueError, match="Hessian"):
        SurrogateMLP(BOUNDS, 0.2, activation=act)


def test_bad_arguments_rejected():
    """Unknown activation/target, bad bounds and empty widths raise ValueError."""
    with pytest.raises(ValueError, match="unknown activation"):
        SurrogateMLP(BOUNDS, 0.2, activation="sine")
    with pytest.raises(ValueError, match="unknown target"):
        SurrogateMLP(BOUNDS, 0.2, target="log")
    with pytest.raises(ValueError, match="lower < upper"):
        SurrogateMLP(BOUNDS.flip(0), 0.2)
    with pytest.raises(ValueError, match="widths"):
        SurrogateMLP(BOUNDS, 0.2, widths=())
    with pytest.raises(ValueError, match="target_std"):
        SurrogateMLP(BOUNDS, 0.2, target_std=0.0)


def test_input_normalization_maps_box_to_unit_cube():
    """Lower bounds map to -1, upper bounds to +1, the center to 0."""
    m = _model()
    u = m.normalize_inputs(torch.stack([BOUNDS[0], BOUNDS[1], BOUNDS.mean(0)]))
    expected = torch.tensor([[-1.0] * 3, [1.0] * 3, [0.0] * 3], dtype=torch.float64)
    torch.testing.assert_close(u, expected, atol=1e-15, rtol=0)


@pytest.mark.parametrize("target", ["log_excess", "inv_sq_excess", "raw"])
def test_output_normalization_and_transform(target):
    """forward/log_excess equal the closed-form maps of the raw net output z with mean m, std s."""
    m = _model(target=target, target_mean=0.7, target_std=0.3)
    x = BOUNDS[0] + (BOUNDS[1] - BOUNDS[0]) * torch.rand(20, 3, dtype=torch.float64)
    z = m.net(m.normalize_inputs(x)).squeeze(-1)
    v = 0.7 + 0.3 * z
    y, t = m(x), m.log_excess(x)
    if target == "log_excess":
        torch.testing.assert_close(t, v)
        torch.testing.assert_close(y, 0.2 + torch.exp(v))
    elif target == "inv_sq_excess":
        torch.testing.assert_close(t, -0.5 * torch.log(v))
        torch.testing.assert_close(y, 0.2 + v.rsqrt())
    else:
        torch.testing.assert_close(y, v)
        torch.testing.assert_close(t, torch.log(v - 0.2))
    # y = f_inf + exp(t) for every target where y > f_inf
    torch.testing.assert_close(y, 0.2 + torch.exp(t))


def test_single_point_gives_scalar_and_hessian_is_d_by_d():
    """A d-vector input gives a scalar, so the Hessian of log_excess is d x d and symmetric."""
    m = _model()
    x0 = BOUNDS.mean(0)
    assert m(x0).shape == () and m.log_excess(x0).shape == ()
    h = torch.autograd.functional.hessian(m.log_excess, x0)
    assert h.shape == (3, 3)
    torch.testing.assert_close(h, h.T, atol=1e-10, rtol=1e-10)
    assert h.abs().max() > 0  # smooth activation: curvature is not identically zero


@pytest.mark.parametrize("activation", ["silu", "tanh", "softplus", "gelu"])
def test_log_excess_twice_differentiable(activation):
    """First and second derivatives of log_excess and forward match finite differences."""
    m = _model(activation=activation, target_std=0.5)
    x = BOUNDS.mean(0) + 0.1 * (BOUNDS[1] - BOUNDS[0]) * torch.randn(4, 3, dtype=torch.float64)
    x.requires_grad_(True)
    assert torch.autograd.gradcheck(m.log_excess, (x,))
    assert torch.autograd.gradgradcheck(m.log_excess, (x,))
    assert torch.autograd.gradgradcheck(m, (x,))


def test_float32_input_to_float64_model_and_float32_model():
    """float32 inputs work for float64 models (cast) and float32 models give float32 outputs."""
    m = _model()
    x = BOUNDS.mean(0, keepdim=True)
    assert m(x.float()).dtype == torch.float64
    torch.testing.assert_close(m(x.float()), m(x.float().double()))
    m32 = _model().float()
    with torch.no_grad():
        y32 = m32(x)
    assert y32.dtype == torch.float32
    assert math.isclose(float(y32), float(m(x).detach()), rel_tol=1e-5)


def test_bad_inputs_rejected():
    """Wrong number of knobs or NaN entries raise ValueError."""
    m = _model()
    with pytest.raises(ValueError, match="shape"):
        m(torch.zeros(5, 4))
    with pytest.raises(ValueError, match="NaN"):
        m(torch.tensor([[0.0, float("nan"), 0.0]]))
    with pytest.raises(ValueError, match="shape"):
        m.log_excess(torch.zeros(2, 3, 1))
