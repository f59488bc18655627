"""Tests of the multi-start maximum search."""

import pytest
import torch

from pigp_torch.prior import find_optimum


def test_finds_bump_centre(bump):
    """The maximum of a Gaussian bump is found at its centre to 1e-6 (knob units)."""
    x0, f_x0 = find_optimum(bump, bump.bounds, n_starts=8, seed=0)
    assert (x0 - bump.mu).abs().max() < 1e-6
    assert f_x0 == pytest.approx(bump.f_inf + bump.A, rel=1e-12)


def _two_bumps(X):
    """Local maximum 1.0 at (-0.5, -0.5), global maximum 2.0 at (0.6, 0.6)."""
    a = torch.exp(-((X + 0.5) ** 2).sum(-1) / 0.02)
    b = 2.0 * torch.exp(-((X - 0.6) ** 2).sum(-1) / 0.02)
    return a + b


def test_multi_start_finds_global_and_is_deterministic():
    """Multi-start finds the higher of two bumps, and the same seed gives the same result."""
    bounds = torch.tensor([[-1.0, -1.0], [1.0, 1.0]], dtype=torch.float64)
    x0, f0 = find_optimum(_two_bumps, bounds, n_starts=16, seed=3)
    x1, f1 = find_optimum(_two_bumps, bounds, n_starts=16, seed=3)
    assert torch.equal(x0, x1) and f0 == f1
    torch.testing.assert_close(x0, torch.tensor([0.6, 0.6], dtype=torch.float64), atol=1e-6, rtol=0)
    assert f0 == pytest.approx(2.0, abs=1e-9)


def test_x_init_alone_climbs_its_own_hill():
    """With no Sobol starts, a start near the local bump ends on the local maximum."""
    bounds = torch.tensor([[-1.0, -1.0], [1.0, 1.0]], dtype=torch.float64)
    x0, f0 = find_optimum(_two_bumps, bounds, n_starts=0, x_init=torch.tensor([-0.4, -0.4]))
    torch.testing.assert_close(
        x0, torch.tensor([-0.5, -0.5], dtype=torch.float64), atol=1e-5, rtol=0
    )
    assert f0 == pytest.approx(1.0, abs=1e-6)


def test_optimum_on_bound():
    """A maximum outside the box is clipped to the box's face (bounds are respected)."""
    bounds = torch.tensor([[-1.0, -1.0], [1.0, 1.0]], dtype=torch.float64)
    x0, _ = find_optimum(lambda X: -((X - 2.0) ** 2).sum(-1), bounds, n_starts=4)
    torch.testing.assert_close(x0, torch.ones(2, dtype=torch.float64), atol=1e-10, rtol=0)


@pytest.mark.parametrize(
    ("bounds", "kwargs", "match"),
    [
        (torch.tensor([[1.0, 0.0], [0.0, 1.0]]), {}, "lower bound"),
        (torch.zeros(3, 2), {}, "shape"),
        (torch.tensor([[0.0, 0.0], [1.0, 1.0]]), {"n_starts": 0}, "starting point"),
        (torch.tensor([[0.0, 0.0], [1.0, 1.0]]), {"x_init": torch.zeros(3)}, "x_init"),
    ],
)
def test_bad_inputs(bounds, kwargs, match):
    """Inverted or misshaped bounds, no starts, or a wrong-size x_init raise ValueError."""
    with pytest.raises(ValueError, match=match):
        find_optimum(lambda X: -(X**2).sum(-1), bounds, **kwargs)


def test_find_optimum_with_closed_form_gradient_equals_the_autograd_search():
    """``with_grad=True`` (f returns values and gradients) follows the same L-BFGS-B path as
    autograd on a rotated quadratic with its peak inside a box: same end point to 1e-8."""
    g = torch.Generator().manual_seed(0)
    A = torch.randn(4, 4, generator=g, dtype=torch.float64)
    P = A @ A.T + torch.eye(4, dtype=torch.float64)
    peak = torch.tensor([0.3, -0.2, 0.1, 0.5], dtype=torch.float64)
    bounds = torch.tensor([[-1.0] * 4, [1.0] * 4], dtype=torch.float64)

    def f(X):
        D = X - peak
        return -0.5 * ((D @ P) * D).sum(-1)

    def f_and_grad(X):
        D = X - peak
        return -0.5 * ((D @ P) * D).sum(-1), -(D @ P)

    x_ref, v_ref = find_optimum(f, bounds, n_starts=4, seed=1)
    x, v = find_optimum(f_and_grad, bounds, n_starts=4, seed=1, with_grad=True)
    torch.testing.assert_close(x, x_ref, rtol=0, atol=1e-8)
    torch.testing.assert_close(x, peak, rtol=0, atol=1e-6)
    assert v == pytest.approx(v_ref, abs=1e-12)
