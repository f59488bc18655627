"""Tests of the physics-informed GP builder against the closed-form GP posterior."""

import pytest
import torch

from pigp_torch.models import physics_informed_gp
from pigp_torch.prior import PhysicsPrior

D = 3


def _prior(noise=0.1, amplitude=1.5**2 / 12):
    g = torch.Generator().manual_seed(0)
    A = torch.randn(D, D, generator=g, dtype=torch.float64)
    P = (A @ A.T + D * torch.eye(D, dtype=torch.float64)) * 1e4  # lengths ~ 0.005 knob units
    return PhysicsPrior(
        x0=torch.zeros(D, dtype=torch.float64),
        f_x0=1.7,
        f_inf=0.2,
        precision=P,
        amplitude=amplitude,
        noise=noise,
        knob_names=["a", "b", "c"],
        bounds=torch.tensor([[-0.015] * D, [0.015] * D], dtype=torch.float64),
    )


def _data(n=8, seed=1):
    g = torch.Generator().manual_seed(seed)
    X = 0.006 * torch.randn(n, D, generator=g, dtype=torch.float64)
    Y = 0.2 + 1.5 * torch.rand(n, generator=g, dtype=torch.float64)
    return X, Y


def _kernel_matrix(prior, kernel, A, B, alpha=0.5):
    Dl = A[:, None, :] - B[None, :, :]
    q = torch.einsum("nmi,ij,nmj->nm", Dl, prior.precision, Dl)
    if kernel == "rbf":
        return prior.amplitude * torch.exp(-0.5 * q)
    return prior.amplitude * (1 + q / (2 * alpha)) ** (-alpha)


@pytest.mark.parametrize("kernel", ["rbf", "rq"])
@pytest.mark.parametrize("mean", ["f_inf", "zero", 0.7])
def test_posterior_matches_closed_form(kernel, mean):
    """Posterior mean and variance equal m + K*^T (K + sn^2 I)^-1 (y - m) etc. to 1e-8."""
    prior = _prior()
    X, Y = _data()
    Xs = 0.006 * torch.randn(5, D, generator=torch.Generator().manual_seed(9)).double()
    model = physics_informed_gp(X, Y, prior, kernel=kernel, mean=mean)
    post = model.posterior(Xs)
    m = {"f_inf": prior.f_inf, "zero": 0.0}.get(mean, mean)
    K = _kernel_matrix(prior, kernel, X, X) + prior.noise**2 * torch.eye(len(X)).double()
    Ks = _kernel_matrix(prior, kernel, X, Xs)
    mu = m + Ks.T @ torch.linalg.solve(K, Y - m)
    var = prior.amplitude - (Ks * torch.linalg.solve(K, Ks)).sum(0)
    torch.testing.assert_close(post.mean.squeeze(-1), mu, rtol=0, atol=1e-8)
    torch.testing.assert_close(post.variance.squeeze(-1), var, rtol=0, atol=1e-8)
    # data must actually pull the posterior away from the prior for the check to mean anything
    assert (mu - m).abs().max() > 0.1 and var.min() < 0.7 * prior.amplitude
    cov = post.mvn.covariance_matrix
    cov_ref = _kernel_matrix(prior, kernel, Xs, Xs) - Ks.T @ torch.linalg.solve(K, Ks)
    torch.testing.assert_close(cov, cov_ref, rtol=0, atol=1e-8)


def test_hyperparameters_fixed_and_frozen():
    """Outputscale, mean and noise equal the prior's; nothing is trainable or changes on use."""
    prior = _prior(noise=0.04, amplitude=0.1)  # 0.1 and 0.2 are not float32-representable
    X, Y = _data()
    model = physics_informed_gp(X, Y, prior)
    assert not model.training
    assert all(not p.requires_grad for p in model.parameters())
    assert model.covar_module.outputscale.item() == pytest.approx(prior.amplitude, rel=1e-12)
    assert model.mean_module.constant.item() == pytest.approx(prior.f_inf, rel=1e-12)
    torch.testing.assert_close(
        model.likelihood.noise, torch.full((8,), 0.04**2, dtype=torch.float64), rtol=1e-12, atol=0
    )
    torch.testing.assert_close(model.covar_module.base_kernel.precision, prior.precision)
    before = {k: v.clone() for k, v in model.state_dict().items()}
    Xs = torch.zeros(4, D, dtype=torch.float64, requires_grad=True)
    model.posterior(Xs).mean.sum().backward()  # as an acquisition optimizer would
    after = model.state_dict()
    assert before.keys() == after.keys()
    assert all(torch.equal(before[k], after[k]) for k in before)


def test_far_away_prediction_reverts_to_prior_mean():
    """Far from the data the mean is f_inf by default, 0 with mean='zero'; variance is sigma_f^2."""
    prior = _prior()
    X, Y = _data()
    far = torch.full((1, D), 0.2, dtype=torch.float64)  # ~40 correlation lengths away
    post = physics_informed_gp(X, Y, prior).posterior(far)
    assert post.mean.item() == pytest.approx(prior.f_inf, abs=1e-12)
    assert post.variance.item() == pytest.approx(prior.amplitude, rel=1e-12)
    assert physics_informed_gp(X, Y, prior, mean="zero").posterior(far).mean.item() == 0.0


def test_y_shapes_and_input_gradient():
    """Y of shape n or n x 1 give the same model; the mean's input gradient passes gradcheck."""
    prior = _prior()
    X, Y = _data()
    m1 = physics_informed_gp(X, Y, prior)
    m2 = physics_informed_gp(X, Y.unsqueeze(-1), prior, kernel="rq")
    m3 = physics_informed_gp(X, Y.unsqueeze(-1), prior)
    Xs = 0.004 * torch.randn(3, D, generator=torch.Generator().manual_seed(2)).double()
    assert torch.equal(m1.posterior(Xs).mean, m3.posterior(Xs).mean)
    for m in (m1, m2):
        x = Xs.clone().requires_grad_(True)
        assert torch.autograd.gradcheck(lambda z, m=m: m.posterior(z).mean, (x,))


@pytest.mark.parametrize(
    ("args", "kwargs", "match"),
    [
        ((torch.zeros(4, 2), torch.zeros(4)), {}, "X must have shape"),
        ((torch.zeros(4, 3), torch.zeros(5)), {}, "Y must have shape"),
        ((torch.zeros(4, 3), torch.full((4,), float("nan"))), {}, "NaN"),
        ((torch.zeros(4, 3), torch.zeros(4)), {"kernel": "matern"}, "kernel"),
        ((torch.zeros(4, 3), torch.zeros(4)), {"mean": "data"}, "mean"),
    ],
)
def test_bad_inputs(args, kwargs, match):
    """Wrong knob count, mismatched Y, NaN, unknown kernel or mean raise ValueError."""
    with pytest.raises(ValueError, match=match):
        physics_informed_gp(*args, _prior(), **kwargs)
