"""Tests of the autograd / finite-difference Hessians and the negative-definite repair."""

import warnings

import pytest
import torch

from pigp_torch.prior import (
    finite_difference_hessian,
    log_excess_hessian,
    repair_negative_definite,
)


def test_log_excess_hessian_closed_form(bump):
    """For a Gaussian bump, H = -P and G = -P (x - mu) exactly, f(x0) is the bump value."""
    x = bump.mu + 0.002
    H, G, f_x0 = log_excess_hessian(bump, x, bump.f_inf)
    torch.testing.assert_close(H, -bump.P, rtol=1e-10, atol=0)
    torch.testing.assert_close(G, -bump.P @ (x - bump.mu), rtol=1e-10, atol=1e-12)
    assert f_x0 == pytest.approx(bump(x.unsqueeze(0)).item(), rel=1e-15)


def test_finite_difference_log_hessian_matches_autograd(bump):
    """Central differences of log(f - f_inf) agree with autograd to 1e-5 relative."""
    x = bump.mu + 0.001
    H_ad, G_ad, f_ad = log_excess_hessian(bump, x, bump.f_inf)
    H_fd, G_fd, f_fd = finite_difference_hessian(bump, x, f_inf=bump.f_inf, step=1e-5)
    assert (H_fd - H_ad).norm() / H_ad.norm() < 1e-5
    assert (G_fd - G_ad).norm() / G_ad.norm() < 1e-5
    assert f_fd == f_ad


def test_finite_difference_plain_hessian_matches_autograd(bump):
    """Without f_inf the stencil differentiates f itself; per-knob steps are accepted."""
    x = bump.mu + 0.001
    d = x.shape[0]
    H_ad = torch.autograd.functional.hessian(lambda z: bump(z.unsqueeze(0))[0], x)
    steps = torch.linspace(5e-6, 2e-5, d, dtype=torch.float64)
    H_fd, G_fd, _ = finite_difference_hessian(bump, x, step=steps)
    assert (H_fd - H_ad).norm() / H_ad.norm() < 1e-5
    G_ad = torch.autograd.functional.jacobian(lambda z: bump(z.unsqueeze(0))[0], x)
    assert (G_fd - G_ad).norm() / G_ad.norm() < 1e-5


def test_finite_difference_uses_one_batched_call():
    """All 1 + 2 d^2 stencil points are evaluated in a single call of f."""
    calls = []

    def f(X):
        calls.append(X.shape)
        return -(X**2).sum(-1)

    H, _, _ = finite_difference_hessian(f, torch.zeros(5, dtype=torch.float64), step=1e-3)
    assert calls == [torch.Size([1 + 2 * 25, 5])]
    torch.testing.assert_close(H, -2 * torch.eye(5, dtype=torch.float64), rtol=0, atol=1e-8)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"step": 0.0}, "step"),
        ({"step": torch.tensor([1e-3, 1e-3])}, "step"),
        ({"f_inf": 10.0}, "f_inf"),
    ],
)
def test_finite_difference_bad_inputs(kwargs, match):
    """Non-positive or wrongly sized steps and f_inf above f raise ValueError."""
    with pytest.raises(ValueError, match=match):
        finite_difference_hessian(lambda X: 1 - (X**2).sum(-1), torch.zeros(3), **kwargs)


def test_log_excess_hessian_rejects_f_inf_above_f():
    """f_inf >= f(x0) makes log(f - f_inf) undefined and raises ValueError."""
    with pytest.raises(ValueError, match="f_inf"):
        log_excess_hessian(lambda X: 1 - (X**2).sum(-1), torch.zeros(2), f_inf=1.0)


def test_log_excess_hessian_rejects_non_finite_hessian():
    """A kink at x0 (sqrt of a squared norm) gives a NaN Hessian and raises ValueError."""
    with pytest.raises(ValueError, match="not finite"):
        log_excess_hessian(lambda X: 2 - (X**2).sum(-1).sqrt(), torch.zeros(2), f_inf=0.0)


def _with_eigenvalues(eig, seed=0):
    Q, _ = torch.linalg.qr(
        torch.randn(len(eig), len(eig), generator=torch.Generator().manual_seed(seed)).double()
    )
    H = Q @ torch.diag(torch.tensor(eig, dtype=torch.float64)) @ Q.T
    return 0.5 * (H + H.T), Q


def test_repair_fixes_one_positive_eigenvalue_and_warns():
    """One positive eigenvalue is clipped to -floor, the rest kept, and a warning reports it."""
    H, Q = _with_eigenvalues([-100.0, -10.0, -1.0, 3.0])
    with pytest.warns(RuntimeWarning, match=r"clipped 1 of 4"):
        H_rep, info = repair_negative_definite(H, rel_floor=1e-6)
    eig = torch.linalg.eigvalsh(H_rep)
    torch.testing.assert_close(
        eig, torch.tensor([-100.0, -10.0, -1.0, -1e-4], dtype=torch.float64), rtol=1e-9, atol=1e-12
    )
    assert info["n_clipped"] == 1
    assert info["floor"] == pytest.approx(1e-4)
    # the change is the removed eigenvalue 3 + 1e-4 along its eigenvector
    expected_change = (3.0 + 1e-4) / torch.linalg.matrix_norm(H).item()
    assert info["relative_change"] == pytest.approx(expected_change, rel=1e-9)
    # eigenvectors are preserved
    torch.testing.assert_close(H_rep @ Q[:, 0], -100.0 * Q[:, 0], rtol=0, atol=1e-10)


def test_repair_leaves_negative_definite_unchanged_without_warning():
    """A negative-definite matrix comes back identical and no warning is raised."""
    H, _ = _with_eigenvalues([-50.0, -5.0, -0.5])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        H_rep, info = repair_negative_definite(H)
    assert torch.equal(H_rep, H)
    assert info["n_clipped"] == 0 and info["relative_change"] == 0.0


@pytest.mark.parametrize(
    ("H", "match"),
    [
        (torch.zeros(3, 3), "zero"),
        (torch.ones(2, 3), "square"),
        (torch.tensor([[-1.0, 0.5], [0.0, -1.0]]), "symmetric"),
        (torch.tensor([[-1.0, float("nan")], [float("nan"), -1.0]]), "NaN"),
    ],
)
def test_repair_bad_inputs(H, match):
    """Zero, non-square, asymmetric or non-finite matrices raise ValueError."""
    with pytest.raises(ValueError, match=match):
        repair_negative_definite(H)
