"""Contract tests run on every full-precision kernel class (closed form, shapes, dtypes)."""

import gpytorch
import numpy as np
import pytest
import torch

from pigp_torch.kernels import FullPrecisionRBFKernel, FullPrecisionRQKernel
from pigp_torch.kernels._base import FullPrecisionKernelBase


def _rbf_np(x1, x2, P):
    d = x1[:, None, :] - x2[None, :, :]
    return np.exp(-0.5 * np.einsum("nmi,ij,nmj->nm", d, P, d))


def _rq_np(alpha):
    def k(x1, x2, P):
        d = x1[:, None, :] - x2[None, :, :]
        q = np.einsum("nmi,ij,nmj->nm", d, P, d)
        return (1.0 + q / (2.0 * alpha)) ** (-alpha)

    return k


# (constructor, numpy reference) for every concrete kernel; new kernels must be added here.
CASES = {
    "rbf": (lambda P: FullPrecisionRBFKernel(P), _rbf_np),
    "rq-0.5": (lambda P: FullPrecisionRQKernel(P, alpha=0.5), _rq_np(0.5)),
    "rq-3": (lambda P: FullPrecisionRQKernel(P, alpha=3.0), _rq_np(3.0)),
}


def test_every_subclass_is_covered():
    """Every concrete FullPrecisionKernelBase subclass appears in the contract cases."""
    covered = {type(make(torch.eye(2))) for make, _ in CASES.values()}
    assert set(FullPrecisionKernelBase.__subclasses__()) == covered


@pytest.mark.parametrize("name", list(CASES))
@pytest.mark.parametrize("d", [1, 4, 13])
def test_closed_form(name, d, spd):
    """The kernel matrix equals the explicit numpy formula at random points to 1e-10."""
    make, ref = CASES[name]
    P = spd(d, cond=100.0, seed=d)
    k = make(P)
    g = torch.Generator().manual_seed(1)
    # points whitened by P so that q is O(1): kernel values spread over (0, 1)
    W = torch.linalg.inv(torch.linalg.cholesky(P)).T / d**0.5
    x1 = 1.5 * torch.randn(7, d, generator=g, dtype=torch.float64) @ W.T
    x2 = 1.5 * torch.randn(5, d, generator=g, dtype=torch.float64) @ W.T
    K = k(x1, x2).to_dense()
    expected = ref(x1.numpy(), x2.numpy(), P.numpy())
    assert K.shape == (7, 5)
    np.testing.assert_allclose(K.detach().numpy(), expected, rtol=0, atol=1e-10)
    # values are spread over (0, 1], so the check is not trivially passed by ones or zeros
    assert expected.max() - expected.min() > 0.3


@pytest.mark.parametrize("name", list(CASES))
def test_stiff_direction_has_shorter_correlation_length(name):
    """Along the stiff eigenvector of P (large eigenvalue) the kernel decays fastest."""
    make, _ = CASES[name]
    Q, _ = torch.linalg.qr(torch.randn(3, 3, generator=torch.Generator().manual_seed(3)).double())
    P = Q @ torch.diag(torch.tensor([100.0, 4.0, 1.0], dtype=torch.float64)) @ Q.T
    k = make(0.5 * (P + P.T))
    r = 0.3
    origin = torch.zeros(1, 3, dtype=torch.float64)
    k_stiff = k(origin, r * Q[:, 0].unsqueeze(0)).to_dense().item()
    k_soft = k(origin, r * Q[:, 2].unsqueeze(0)).to_dense().item()
    assert k_stiff < k_soft
    # the stiff correlation length is 1/sqrt(100) = 0.1, the soft one 1: exact values for RBF
    if isinstance(k, FullPrecisionRBFKernel):
        assert k_stiff == pytest.approx(np.exp(-0.5 * 100 * r**2), rel=1e-12)
        assert k_soft == pytest.approx(np.exp(-0.5 * 1 * r**2), rel=1e-12)


@pytest.mark.parametrize("name", list(CASES))
def test_batch_shapes_and_diag(name, spd):
    """Batched inputs (b x n x d) give b x n x m matrices; diag=True equals the full diagonal."""
    make, ref = CASES[name]
    P = spd(4, seed=7)
    k = make(P)
    x1 = 0.5 * torch.randn(3, 6, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    x2 = 0.5 * torch.randn(3, 5, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(4))
    K = k(x1, x2).to_dense()
    assert K.shape == (3, 6, 5)
    for b in range(3):
        np.testing.assert_allclose(
            K[b].detach().numpy(), ref(x1[b].numpy(), x2[b].numpy(), P.numpy()), atol=1e-10
        )
    # diag of k(x1, x1') with distinct points of equal count
    x1b = x1[:, :5]
    Kd = k(x1b, x2, diag=True)
    assert Kd.shape == (3, 5)
    full = k(x1b, x2).to_dense()
    torch.testing.assert_close(Kd, torch.diagonal(full, dim1=-2, dim2=-1), rtol=0, atol=1e-12)
    # diag of k(x, x) is exactly one
    torch.testing.assert_close(k(x1, x1, diag=True), torch.ones(3, 6, dtype=torch.float64))


@pytest.mark.parametrize("name", list(CASES))
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_dtypes(name, dtype, spd):
    """The output has the input dtype and matches the float64 values to that dtype's precision."""
    make, _ = CASES[name]
    k = make(spd(3, seed=11))
    x = 0.5 * torch.randn(8, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(5))
    K64 = k(x, x).to_dense()
    K = k(x.to(dtype), x.to(dtype)).to_dense()
    assert K.dtype == dtype
    atol = 1e-5 if dtype == torch.float32 else 1e-14
    torch.testing.assert_close(K.double(), K64, rtol=0, atol=atol)


@pytest.mark.parametrize("name", list(CASES))
def test_no_parameters_and_buffers_in_state_dict(name, spd):
    """The kernel has no trainable parameters; the precision travels in the state_dict."""
    make, _ = CASES[name]
    P = spd(4, seed=2)
    k = make(P)
    assert list(k.parameters()) == []
    assert "precision_cholesky" in k.state_dict()
    torch.testing.assert_close(k.precision, P, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("name", list(CASES))
def test_scale_kernel_wrapping(name, spd):
    """ScaleKernel(k) multiplies the matrix by the outputscale and has only that one parameter."""
    make, _ = CASES[name]
    k = make(spd(3, seed=5))
    sk = gpytorch.kernels.ScaleKernel(k).double()
    sk.outputscale = 2.5
    x = torch.randn(6, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(8))
    torch.testing.assert_close(sk(x).to_dense(), 2.5 * k(x).to_dense(), rtol=1e-12, atol=0)
    assert [n for n, _ in sk.named_parameters()] == ["raw_outputscale"]


@pytest.mark.parametrize("name", list(CASES))
def test_gradient_wrt_inputs(name, spd):
    """Input gradients (used by acquisition optimization) pass torch.autograd.gradcheck."""
    make, _ = CASES[name]
    k = make(spd(3, seed=9))
    x2 = torch.randn(4, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    x1 = torch.randn(2, 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x: k(x, x2).to_dense(), (x1,))


@pytest.mark.parametrize("name", list(CASES))
def test_wrong_input_dimension_raises(name, spd):
    """Inputs whose last dimension differs from the precision's size raise ValueError."""
    make, _ = CASES[name]
    k = make(spd(3))
    with pytest.raises(ValueError, match="last dimension 3"):
        k(torch.zeros(2, 4, dtype=torch.float64), torch.zeros(2, 4, dtype=torch.float64)).to_dense()


@pytest.mark.parametrize("cls", [FullPrecisionRBFKernel, FullPrecisionRQKernel])
@pytest.mark.parametrize(
    ("bad", "match"),
    [
        (torch.ones(2, 3), "square"),
        (torch.ones(3), "square"),
        (torch.tensor([[1.0, 0.5], [0.4, 1.0]]), "symmetric"),
        (torch.tensor([[1.0, 2.0], [2.0, 1.0]]), "positive definite"),
        (torch.tensor([[1.0, 0.0], [0.0, 0.0]]), "positive definite"),
        (torch.tensor([[1.0, float("nan")], [float("nan"), 1.0]]), "NaN"),
        (torch.tensor([[1.0, 0.0], [0.0, float("inf")]]), "NaN or inf"),
    ],
)
def test_bad_precision_raises(cls, bad, match):
    """Non-square, asymmetric, indefinite, singular or non-finite precision raises ValueError."""
    with pytest.raises(ValueError, match=match):
        cls(bad)
