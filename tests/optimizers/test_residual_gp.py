"""The residual GP of the observables: its posterior mean against GPyTorch's with the same
hyperparameters, its gradient, when it stays off, and the tracker it corrects on a toy machine
with physics its model lacks."""

from __future__ import annotations

import gpytorch
import pytest
import torch

from pigp_torch.optimizers.residual_gp import MIN_GAIN_NATS, fit_residual_gp

from .test_tracking import TARGET, _toy_optimizer

D = torch.float64
BOUNDS = torch.tensor([[-1.0, -2.0, 0.0], [1.0, 2.0, 0.5]], dtype=D)


def _settings(n: int, seed: int = 0) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    lo, hi = BOUNDS
    return lo + (hi - lo) * torch.rand(n, 3, generator=gen, dtype=D)


def test_noise_alone_leaves_the_model_as_it_is():
    """Residuals that are the stated noise (and tiny ones, a model that explains a noise-free
    machine) give no GP."""
    gen = torch.Generator().manual_seed(1)
    X = _settings(20)
    assert (
        fit_residual_gp(X, 1e-6 * torch.randn(20, 4, generator=gen, dtype=D), BOUNDS, 1e-6) is None
    )
    assert (
        fit_residual_gp(X, 1e-12 * torch.randn(20, 4, generator=gen, dtype=D), BOUNDS, 1e-6) is None
    )
    assert fit_residual_gp(X[:2], torch.ones(2, 4, dtype=D), BOUNDS, 1e-6) is None


def test_the_posterior_mean_is_gpytorch_s_with_the_chosen_hyperparameters():
    """A smooth residual (1e-5 * the first knob, plus an offset): the GP is used, and its
    mean at new settings equals GPyTorch's exact GP (zero mean, RBF on the settings scaled by
    the knobs' ranges, the chosen length, amplitude and noise; in µm, where GPyTorch's jitter
    is negligible) to 1e-7 relative."""
    X = _settings(20)
    truth = torch.stack([1e-5 * X[:, 0], 5e-6 + 0 * X[:, 0]], -1)
    gen = torch.Generator().manual_seed(2)
    R = truth + 1e-7 * torch.randn(20, 2, generator=gen, dtype=D)
    gp = fit_residual_gp(X, R, BOUNDS, 1e-7)
    assert gp is not None and gp.gain_nats >= MIN_GAIN_NATS
    Xs = _settings(7, seed=5)
    mean = gp(Xs)
    scale = BOUNDS[1] - BOUNDS[0]

    class Exact(gpytorch.models.ExactGP):
        def __init__(self, y, lik):
            super().__init__(X / scale, y, lik)
            self.mean = gpytorch.means.ZeroMean()
            self.cov = gpytorch.kernels.ScaleKernel(gpytorch.kernels.RBFKernel())

        def forward(self, z):
            return gpytorch.distributions.MultivariateNormal(self.mean(z), self.cov(z))

    for j in range(2):
        lik = gpytorch.likelihoods.GaussianLikelihood(
            noise_constraint=gpytorch.constraints.GreaterThan(1e-30)
        )
        lik.noise = (1e6 * float(gp.noise[j])) ** 2
        model = Exact(1e6 * R[:, j], lik).to(D)
        model.cov.base_kernel.lengthscale = float(gp.length[j])
        model.cov.outputscale = (1e6 * float(gp.amplitude[j])) ** 2
        model.eval()
        lik.eval()
        with torch.no_grad(), gpytorch.settings.fast_computations(False, False, False):
            ref = model(Xs / scale).mean
        assert torch.allclose(1e6 * mean[:, j], ref, rtol=1e-7, atol=1e-7 * float(ref.abs().max()))
    # it predicts the residual between the readings (to 20 % of its size)
    err = (gp(Xs) - torch.stack([1e-5 * Xs[:, 0], 5e-6 + 0 * Xs[:, 0]], -1)).abs()
    assert float(err.max()) < 2e-6, err


def test_the_mean_is_differentiable_in_the_settings():
    X = _settings(12)
    R = torch.stack([1e-5 * X[:, 0] ** 2, 1e-5 * X[:, 1]], -1)
    gp = fit_residual_gp(X, R, BOUNDS, 1e-7)
    assert gp is not None
    x = _settings(3, seed=9).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda z: gp(z) * 1e5, (x,))


def _machine(X: torch.Tensor) -> torch.Tensor:
    """One knob, two observables (the target is not reachable: the optimum is a compromise of
    the two): the model's first observable lacks a quadratic term."""
    x = X[..., 0]
    return torch.stack([1.3 * x + 0.3 * x**2, 0.8 * x - 0.2], -1)


def _model(X: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    return torch.stack([theta[..., 0] * X[..., 0], theta[..., 1] * X[..., 0] + theta[..., 2]], -1)


@pytest.mark.parametrize("residual_gp", [False, True])
def test_the_tracker_with_the_residual_gp_ends_at_the_machine_s_optimum(residual_gp):
    """The tracker on that machine, read with noise 1e-3: with the option the residual GP is
    used on most asks, and either way the final true MAE is within 2e-4 of the machine's
    optimum (a grid of 20,001 settings); without it no GP is fitted."""
    opt = _toy_optimizer(
        bounds=torch.tensor([[-1.0], [1.0]], dtype=D),
        model=_model,
        center=(1.0, 1.0, 0.0),
        residual_gp=residual_gp,
        noise_probe=0,  # the GP alone: no repeat readings at the first failed check
    )
    gen = torch.Generator().manual_seed(0)
    x = torch.tensor([-0.5], dtype=D)
    for _ in range(40):
        o = _machine(x[None])[0] + 0.001 * torch.randn(2, generator=gen, dtype=D)
        opt.tell(x, float((o - TARGET).abs().mean()), observables=o)
        x = opt.ask()
    grid = torch.linspace(-1, 1, 20001, dtype=D)[:, None]
    best = float((_machine(grid) - TARGET).abs().mean(-1).min())
    final = float((_machine(opt.recommend()[None])[0] - TARGET).abs().mean())
    assert opt.tracking and abs(final - best) < 2e-4, (final, best)
    if residual_gp:
        assert opt.n_residual_asks >= 10, opt.n_residual_asks
    else:
        assert opt.n_residual_asks == 0 and opt.last_residual_gp is None
