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
