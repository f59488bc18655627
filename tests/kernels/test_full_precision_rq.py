"""Tests specific to FullPrecisionRQKernel (heavy tail, RBF limit)."""

import pytest
import torch

from pigp_torch.kernels import FullPrecisionRBFKernel, FullPrecisionRQKernel


def _P():
    return torch.tensor([[3.0, 1.0, 0.2], [1.0, 2.0, 0.1], [0.2, 0.1, 0.5]], dtype=torch.float64)


def test_large_alpha_recovers_rbf():
    """For alpha = 1e6 the RQ kernel equals the RBF kernel with the same precision to 1e-6."""
    x = 2.0 * torch.randn(10, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    K_rq = FullPrecisionRQKernel(_P(), alpha=1e6)(x).to_dense()
    K_rbf = FullPrecisionRBFKernel(_P())(x).to_dense()
    assert K_rbf.min() < 1e-3  # far pairs included, where the tails differ most at small alpha
    torch.testing.assert_close(K_rq, K_rbf, rtol=0, atol=1e-6)


def test_alpha_half_tail_matches_inverse_sqrt():
    """At alpha = 0.5 the kernel is (1 + q)^(-1/2): 0.71, 0.45, 0.32 at 1, 2, 3 sigma."""
    k = FullPrecisionRQKernel(torch.eye(1, dtype=torch.float64), alpha=0.5)
    r = torch.tensor([[1.0], [2.0], [3.0]], dtype=torch.float64)
    vals = k(torch.zeros(1, 1, dtype=torch.float64), r).to_dense().flatten()
    expected = torch.tensor([2**-0.5, 5**-0.5, 10**-0.5], dtype=torch.float64)
    torch.testing.assert_close(vals, expected, rtol=1e-14, atol=0)
    rbf = FullPrecisionRBFKernel(torch.eye(1, dtype=torch.float64))
    rbf_vals = rbf(torch.zeros(1, 1, dtype=torch.float64), r).to_dense().flatten()
    assert (vals > rbf_vals).all()


def test_same_curvature_at_origin_as_rbf():
    """Near zero distance RQ and RBF agree to second order in r (same precision meaning)."""
    x = 1e-3 * torch.tensor([[0.3, -0.2, 0.5]], dtype=torch.float64)
    o = torch.zeros(1, 3, dtype=torch.float64)
    q = (x @ _P() @ x.T).item()
    k_rq = FullPrecisionRQKernel(_P(), alpha=0.5)(o, x).to_dense().item()
    k_rbf = FullPrecisionRBFKernel(_P())(o, x).to_dense().item()
    assert abs(k_rq - k_rbf) < 2 * q**2
    assert 1 - k_rbf == pytest.approx(q / 2, rel=1e-5)


@pytest.mark.parametrize("alpha", [0.0, -1.0, float("nan"), float("inf")])
def test_bad_alpha_raises(alpha):
    """alpha must be finite and positive."""
    with pytest.raises(ValueError, match="alpha"):
        FullPrecisionRQKernel(_P(), alpha=alpha)


def test_alpha_is_a_buffer_not_parameter():
    """alpha is stored as a buffer and is not trainable."""
    k = FullPrecisionRQKernel(_P(), alpha=2.0)
    assert list(k.parameters()) == []
    assert k.state_dict()["alpha"].item() == 2.0
