"""Tests specific to FullPrecisionRBFKernel."""

import gpytorch
import torch

from pigp_torch.kernels import FullPrecisionRBFKernel


def test_diagonal_precision_equals_gpytorch_ard_rbf():
    """With P = diag(1/l²) the kernel equals GPyTorch's ARD RBFKernel with lengthscales l."""
    ls = torch.tensor([0.3, 1.5, 0.7], dtype=torch.float64)
    k = FullPrecisionRBFKernel(torch.diag(ls**-2))
    ref = gpytorch.kernels.RBFKernel(ard_num_dims=3).double()
    ref.lengthscale = ls
    x1 = torch.randn(5, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    x2 = torch.randn(4, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    torch.testing.assert_close(k(x1, x2).to_dense(), ref(x1, x2).to_dense(), rtol=0, atol=1e-12)


def test_precision_cast_and_device_follow_module():
    """Casting the module to float32 keeps the kernel values (the buffer follows .to())."""
    P = torch.tensor([[4.0, 1.0], [1.0, 2.0]], dtype=torch.float64)
    k = FullPrecisionRBFKernel(P)
    x = torch.tensor([[0.0, 0.0], [0.5, -0.5]], dtype=torch.float32)
    k32 = FullPrecisionRBFKernel(P).float()
    assert k32.precision_cholesky.dtype == torch.float32
    expected = torch.exp(torch.tensor(-0.5 * (0.25 * 4 - 2 * 0.25 * 1 + 0.25 * 2)))
    torch.testing.assert_close(k32(x).to_dense()[0, 1], expected.float(), rtol=1e-6, atol=0)
    torch.testing.assert_close(k(x).to_dense()[0, 1], expected.float(), rtol=1e-6, atol=0)
