"""The Lyapunov solver of the fast model: equation residual, backends agree, derivatives exact."""

import torch

from pigp_torch.simulation.linear_model import lyapunov_doubling


def damped_map(n, seed):
    g = torch.Generator().manual_seed(seed)
    Q, _ = torch.linalg.qr(torch.randn(n, 6, 6, generator=g, dtype=torch.float64))
    return 0.97 * Q  # spectral radius 0.97: damped


def diffusion(n, seed):
    g = torch.Generator().manual_seed(seed)
    A = torch.randn(n, 6, 6, generator=g, dtype=torch.float64)
    return A @ A.transpose(1, 2)


def test_solution_satisfies_equation():
    """R = M R M^T + B holds to machine precision and the residual flag says 'damped'."""
    M, B = damped_map(4, 0), diffusion(4, 1)
    R, residual = lyapunov_doubling(M, B, 12)
    assert torch.allclose(R, M @ R @ M.transpose(1, 2) + B, rtol=1e-12, atol=1e-10)
    assert (residual < 1e-50).all()  # 0.97^4096 ≈ 6e-55


def test_numpy_and_torch_paths_agree():
    """The numpy-backed CPU float64 path equals the pure-torch path (used on other devices)."""
    M, B = damped_map(3, 2), diffusion(3, 3)
    R64, _ = lyapunov_doubling(M, B, 12)
    R32, _ = lyapunov_doubling(M.float(), B.float(), 12)
    assert torch.allclose(R64.float(), R32, rtol=1e-4, atol=1e-3)


def test_undamped_map_is_flagged():
    """A map with an eigenvalue outside the unit circle gives a large (or inf) residual."""
    M, B = damped_map(1, 4) / 0.97 * 1.01, diffusion(1, 5)
    _, residual = lyapunov_doubling(M, B, 12)
    assert not (residual < 1e-6).all()


def test_gradients_through_solver():
    """First and second derivatives w.r.t. M and B match finite differences."""
    M = damped_map(1, 6).requires_grad_(True)
    B = diffusion(1, 7).requires_grad_(True)

    def f(M, B):
        return lyapunov_doubling(M, B, 10)[0]

    assert torch.autograd.gradcheck(f, (M, B), eps=1e-6, atol=1e-5, rtol=1e-4)
    assert torch.autograd.gradgradcheck(f, (M, B), eps=1e-6, atol=1e-4, rtol=1e-3)
