"""The fast model's pieces: Lyapunov solver, eigen-emittances from invariants, knob updates."""

import math

import numpy as np
import pytest
import torch

from pigp_torch.machines.ring.linear_model import (
    SegmentModel,
    _congruence,
    _knob_cols,
    _knob_rows,
    doubling_count,
    equilibrium,
    equilibrium_chunked,
)
from pigp_torch.machines.ring.lyapunov import J6, eigen_emittances, lyapunov_doubling

J = torch.as_tensor(J6)


def damped_map(n, seed):
    g = torch.Generator().manual_seed(seed)
    Q, _ = torch.linalg.qr(torch.randn(n, 6, 6, generator=g, dtype=torch.float64))
    return 0.97 * Q  # spectral radius 0.97: damped


def diffusion(n, seed):
    g = torch.Generator().manual_seed(seed)
    A = torch.randn(n, 6, 6, generator=g, dtype=torch.float64)
    return A @ A.transpose(1, 2)


def beam_with_emittances(eps, seed, spread=0.6):
    r"""``R = S diag(ε1, ε1, ε2, ε2, ε3, ε3) S^T`` with a random symplectic ``S = exp(J H)``.

    Its eigen-emittances are exactly ``eps`` (Williamson normal form), whatever ``S``.
    """
    g = torch.Generator().manual_seed(seed)
    H = spread * torch.randn(len(eps), 6, 6, generator=g, dtype=torch.float64)
    S = torch.linalg.matrix_exp(J @ (H + H.transpose(1, 2)))
    d = torch.as_tensor(eps, dtype=torch.float64).repeat_interleave(2, dim=-1)
    return S @ torch.diag_embed(d) @ S.transpose(1, 2)


def eigvalsh_emittances(R):
    """The former path: Hermitian eigenvalues of i L^T J L (reference for the invariants)."""
    L = torch.linalg.cholesky(R)
    return torch.linalg.eigvalsh(1j * (L.transpose(1, 2) @ J @ L).to(torch.complex128))[:, 3:]


# ----------------------------------------------------------------------------- Lyapunov
def test_solution_satisfies_equation():
    """R = M R M^T + B holds to machine precision and the residual flag says 'damped'."""
    M, B = damped_map(4, 0), diffusion(4, 1)
    R, residual = lyapunov_doubling(M, B, 12)
    assert torch.allclose(R, M @ R @ M.transpose(1, 2) + B, rtol=1e-12, atol=1e-10)
    assert (residual < 1e-50).all()  # 0.97^4096 ≈ 6e-55


def test_numpy_and_torch_paths_agree():
    """numpy (CPU float64) = torch float64 (the GPU path) to 1e-13; float32 torch to 1e-4."""
    M, B = damped_map(3, 2), diffusion(3, 3)
    R64, res64 = lyapunov_doubling(M, B, 12)
    Rt, rest = lyapunov_doubling(M, B, 12, torch_only=True)
    assert torch.allclose(R64, Rt, rtol=1e-13, atol=1e-12)
    assert torch.allclose(res64, rest, rtol=1e-6, atol=1e-300)
    R32, _ = lyapunov_doubling(M.float(), B.float(), 12)
    assert torch.allclose(R64.float(), R32, rtol=1e-4, atol=1e-3)


def test_undamped_map_is_flagged():
    """A map with an eigenvalue outside the unit circle gives a large (or inf) residual."""
    M, B = damped_map(1, 4) / 0.97 * 1.01, diffusion(1, 5)
    _, residual = lyapunov_doubling(M, B, 12)
    assert not (residual < 1e-6).all()


@pytest.mark.parametrize("torch_only", [False, True])
def test_gradients_through_solver(torch_only):
    """First and second derivatives w.r.t. M and B match finite differences (both backends)."""
    M = damped_map(1, 6).requires_grad_(True)
    B = diffusion(1, 7).requires_grad_(True)

    def f(M, B):
        return lyapunov_doubling(M, B, 10, torch_only=torch_only)[0]

    assert torch.autograd.gradcheck(f, (M, B), eps=1e-6, atol=1e-5, rtol=1e-4)
    assert torch.autograd.gradgradcheck(f, (M, B), eps=1e-6, atol=1e-4, rtol=1e-3)


def test_doubling_count_from_damping():
    """2^k (1 - ρ) ≥ 32: ρ = 0.99 needs 2^k ≥ 3200, i.e. k = 12; an undamped ring is refused."""
    c, s = math.cos(0.3), math.sin(0.3)
    rot = np.kron(np.eye(3), np.array([[c, s], [-s, c]]))
    assert doubling_count(0.99 * rot) == 12
    assert doubling_count(0.99 * rot, exponent=16.0) == 11
    with pytest.raises(ValueError, match="not damped"):
        doubling_count(rot)


# ----------------------------------------------------------------------------- emittances
def test_invariants_recover_known_emittances_over_twelve_decades():
    """Williamson-form beams with εy/εz down to 3e-7 (εy²/εz² = 1e-13): all three to 1e-8.

    (These random beams have condition numbers up to 1.5e9, which limits any method to ~1e-9;
    the former eigvalsh path is checked to the same tolerance.)
    """
    eps = torch.tensor(
        [[1.6e-12, 1.7e-8, 4.6e-6], [1.2e-10, 1.7e-8, 4.6e-6], [0.5, 1.0, 2.0], [1e-3, 0.3, 0.31]],
        dtype=torch.float64,
    )
    R = beam_with_emittances(eps, seed=0)
    got = eigen_emittances(R)
    assert torch.allclose(got, eps, rtol=1e-8, atol=0)
    assert torch.allclose(eigvalsh_emittances(R), eps, rtol=1e-8, atol=0)  # the former path


def test_invariants_match_eigvalsh_on_the_ring(sim):
    """At random knob settings the invariants equal the Hermitian-eigenvalue path to 1e-9."""
    R = ring_beam_matrices(sim, 64, seed=1)
    assert torch.allclose(eigen_emittances(R), eigvalsh_emittances(R), rtol=1e-9, atol=0)


def test_emittance_derivatives():
    """Closed-form roots are twice differentiable: gradcheck and gradgradcheck in R."""
    R = beam_with_emittances(torch.tensor([[0.4, 1.0, 2.5]]), seed=3, spread=0.3)
    R = R.requires_grad_(True)

    def f(R):
        return eigen_emittances(0.5 * (R + R.transpose(1, 2)))

    assert torch.autograd.gradcheck(f, (R,), eps=1e-6, atol=1e-6, rtol=1e-4)
    assert torch.autograd.gradgradcheck(f, (R,), eps=1e-6, atol=1e-5, rtol=1e-3)


def test_emittance_gradient_equals_eigvalsh_gradient(sim):
    """d εy / d R from the invariants equals that of the eigenvalue path (1e-6 relative)."""
    R = ring_beam_matrices(sim, 4, seed=2).requires_grad_(True)
    (g1,) = torch.autograd.grad(eigen_emittances(R)[:, 0].sum(), R)
    (g2,) = torch.autograd.grad(eigvalsh_emittances(R)[:, 0].sum(), R)
    g1, g2 = 0.5 * (g1 + g1.transpose(1, 2)), 0.5 * (g2 + g2.transpose(1, 2))
    assert ((g1 - g2).norm() / g2.norm()) < 1e-6


# ----------------------------------------------------------------------------- building blocks
def test_knob_updates_equal_matrix_products():
    """Row/column updates = K X, X K^T with K = I + aE (in place and out of place)."""
    g = torch.Generator().manual_seed(0)
    X = torch.randn(5, 6, 6, generator=g, dtype=torch.float64)
    a = torch.randn(5, 1, generator=g, dtype=torch.float64)
    E = torch.zeros(6, 6, dtype=torch.float64)
    E[1, 2], E[3, 0] = 1.0, -0.5
    terms = [(1, 2, 1.0), (3, 0, -0.5)]
    K = torch.eye(6, dtype=torch.float64) + a[:, :, None] * E
    for inplace, spec in ((True, terms), (False, E)):
        assert torch.allclose(_knob_rows(X.clone(), a, spec, inplace), K @ X, atol=1e-15)
        assert torch.allclose(_knob_cols(X.clone(), a, spec, inplace), X @ K.mT, atol=1e-15)
    S, D = damped_map(1, 8)[0], diffusion(1, 9)[0]
    kron_t = torch.kron(S, S).T.contiguous()
    assert torch.allclose(_congruence(X, kron_t, D), S @ X @ S.T + D, atol=1e-14)


def test_segment_model_refuses_unsupported_knob_generator(sim):
    """A knob matrix whose written rows are also read (E @ E != 0) is refused."""
    m = sim._m["model"]
    E = torch.zeros(6, 6, dtype=torch.float64)
    E[1, 2], E[2, 1] = 1.0, 1.0
    with pytest.raises(ValueError, match="must not read the rows it writes"):
        SegmentModel(m.S, m.D, E, m.w_obs, m.c_obs, m.weights, m.n_doubling)


# ----------------------------------------------------------------------------- whole model
@pytest.fixture(scope="module")
def sim():
    from pigp_torch.simulation import Spear3Coupling

    return Spear3Coupling(error_seed=1)


def settings(sim, n, seed):
    """``n`` random settings in the knob box, as the segment model takes them (K1s·L, 1/m)."""
    g = torch.Generator().manual_seed(seed)
    amps = (2 * torch.rand(n, sim.dim, generator=g, dtype=torch.float64) - 1) * sim.bounds[1]
    return sim.k1sl(amps)


def ring_beam_matrices(sim, n, seed):
    """Equilibrium beam matrices of the ring at ``n`` random settings (via the torch path)."""
    m, x = sim._m["model"], settings(sim, n, seed)[:, sim._m["order"]]
    cap = {}
    import pigp_torch.machines.ring.linear_model as lm

    orig = lm.lyapunov_doubling

    def spy(*args, **kw):
        out = orig(*args, **kw)
        cap["R"] = out[0]
        return out

    try:
        lm.lyapunov_doubling = spy
        equilibrium(m, x, emittances=False)
    finally:
        lm.lyapunov_doubling = orig
    return cap["R"]


def test_torch_only_path_equals_default(sim):
    """The device-agnostic path (what a GPU runs) equals the numpy-backed CPU path to 1e-11."""
    m, x = sim._m["model"], settings(sim, 40, seed=3)
    a, b = equilibrium(m, x), equilibrium(m, x, torch_only=True)
    assert torch.equal(a.stable, b.stable)
    assert torch.allclose(a.eps, b.eps, rtol=1e-11, atol=0)
    assert torch.allclose(a.inv_sigma_xy, b.inv_sigma_xy, rtol=1e-12, atol=0)


def test_grad_mode_equals_in_place_mode(sim):
    """With autograd (out-of-place updates) the values equal the in-place fast path (1e-11).

    Round-off only: the two paths order operations differently, and how far that shows depends
    on the CPU's vector kernels (within 1e-13 where the test was written, 8e-13 on an AMD EPYC).
    """
    m, x = sim._m["model"], settings(sim, 6, seed=4)
    with torch.no_grad():
        fast = equilibrium(m, x)
    slow = equilibrium(m, x.clone().requires_grad_(True))
    assert torch.allclose(fast.eps, slow.eps.detach(), rtol=1e-11, atol=0)
    assert torch.allclose(fast.inv_sigma_xy, slow.inv_sigma_xy.detach(), rtol=1e-11, atol=0)


def test_unstable_row_keeps_gradients_of_others_finite(sim):
    """A batch with an unstable setting: NaN outputs there, finite gradients for the others."""
    m = sim._m["model"]
    x = settings(sim, 3, seed=5)
    x[1] = 0.5  # far outside the box: no stable beam
    x.requires_grad_(True)
    st = equilibrium(m, x)
    assert st.stable.tolist() == [True, False, True]
    assert torch.isnan(st.eps[1]).all() and torch.isnan(st.inv_sigma_xy[1])
    loss = st.inv_sigma_xy[[0, 2]].sum() + st.eps[[0, 2], 0].sum() * 1e10
    (grad,) = torch.autograd.grad(loss, x)
    assert torch.isfinite(grad).all() and (grad[1] == 0).all() and (grad[0] != 0).any()


def test_chunked_and_threaded_evaluation(sim):
    """Chunks on 2 threads equal one piece (1e-12) and torch's thread count is restored."""
    m, x = sim._m["model"], settings(sim, 50, seed=6)
    with torch.no_grad():
        whole = equilibrium(m, x)
        threads = torch.get_num_threads()
        par = equilibrium_chunked(m, x, chunk=7, workers=2)
        assert torch.get_num_threads() == threads
    assert torch.equal(whole.stable, par.stable)
    assert torch.allclose(whole.eps, par.eps, rtol=1e-12, atol=0)
    assert torch.allclose(whole.inv_sigma_xy, par.inv_sigma_xy, rtol=1e-12, atol=0)
    # overlapping callers (e.g. two server threads) leave torch's thread count as it was
    import threading

    torch.set_num_threads(2)
    try:
        with torch.no_grad():
            runs = [
                threading.Thread(target=equilibrium_chunked, args=(m, x), kwargs=kw)
                for kw in ({"chunk": 5, "workers": 2}, {"chunk": 3, "workers": 2})
            ]
            for t in runs:
                t.start()
            for t in runs:
                t.join(timeout=60)
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(threads)
    with pytest.raises(ValueError, match="chunk and workers"):
        equilibrium_chunked(m, x, chunk=0)
    with pytest.raises(ValueError, match="13 columns"):
        equilibrium(m, x[:, :5])
