"""Contract of every posterior of the Bayesian-optimization core.

Each posterior in :func:`tests.contracts.parts.posteriors` inherits these checks: mean and
standard deviation equal its BoTorch twin's (``SingleTaskGP`` with the same kernel and noise
where the two overlap), and its derivatives equal autograd's of the twin. A new posterior is one
more entry there.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pigp_torch.models.posterior import Posterior
from tests.contracts.parts import DT, HALF, make_prior, posteriors, readings

PRIOR = make_prior()
X, Y = readings(PRIOR)
POSTERIORS = posteriors(PRIOR, X, Y)
NAMES = sorted(POSTERIORS)


def _points():
    g = torch.Generator().manual_seed(7)
    return (torch.rand(6, X.shape[1], generator=g, dtype=DT) * 2 - 1) * HALF


def _twin_moments(twin, Xs: torch.Tensor):
    post = twin.posterior(Xs.unsqueeze(-2))
    return post.mean.reshape(-1), post.variance.reshape(-1).clamp_min(1e-12).sqrt()


@pytest.mark.parametrize("name", NAMES)
def test_is_a_posterior(name):
    post = POSTERIORS[name][0]
    assert isinstance(post, Posterior)
    assert post.max_order in (1, 2)
    assert post.train_mean(X).shape == (X.shape[0],)


@pytest.mark.parametrize("name", NAMES)
def test_mean_and_std_equal_the_botorch_twin(name):
    post, twin, _ = POSTERIORS[name]
    Xs = _points()
    p = post.predict(Xs.numpy(), 0)
    with torch.no_grad():
        mean, std = _twin_moments(twin, Xs)
    np.testing.assert_allclose(p.mean, mean.numpy(), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(p.std, std.numpy(), rtol=1e-7, atol=1e-12)
    np.testing.assert_allclose(p.variance, std.numpy() ** 2, rtol=1e-7, atol=1e-15)


def test_the_exact_gps_equal_singletaskgp_at_the_data_too():
    """At the told points (variance near the noise floor) the incremental GP equals BoTorch."""
    for name in ("incremental", "botorch"):
        post, twin, same = POSTERIORS[name]
        assert same
        with torch.no_grad():
            mean, _ = _twin_moments(twin, X)
        np.testing.assert_allclose(post.predict(X.numpy(), 0).mean, mean.numpy(), rtol=1e-9)
        np.testing.assert_allclose(np.asarray(post.train_mean(X)), mean.numpy(), rtol=1e-9)


@pytest.mark.parametrize("name", NAMES)
def test_derivatives_equal_autograd(name):
    post, twin, _ = POSTERIORS[name]
    Xs = _points().requires_grad_(True)
    mean, std = _twin_moments(twin, Xs)
    dmean = torch.autograd.grad(mean.sum(), Xs, retain_graph=True)[0].numpy()
    dstd = torch.autograd.grad(std.sum(), Xs)[0].numpy()
    p = post.predict(Xs.detach().numpy(), 1)
    scale = np.abs(dmean).max()
    np.testing.assert_allclose(p.dmean, dmean, rtol=1e-6, atol=1e-9 * scale)
    np.testing.assert_allclose(p.dstd, dstd, rtol=1e-6, atol=1e-9 * np.abs(dstd).max())
    if post.max_order < 2:
        return
    p2 = post.predict(Xs.detach().numpy(), 2)
    for i in range(Xs.shape[0]):
        x = Xs[i].detach()
        hm = torch.autograd.functional.hessian(lambda z: _twin_moments(twin, z[None])[0][0], x)
        hs = torch.autograd.functional.hessian(lambda z: _twin_moments(twin, z[None])[1][0], x)
        np.testing.assert_allclose(p2.hmean[i], hm.numpy(), rtol=1e-6, atol=1e-9 * hm.abs().max())
        np.testing.assert_allclose(p2.hstd[i], hs.numpy(), rtol=1e-6, atol=1e-9 * hs.abs().max())
