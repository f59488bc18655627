"""Tests of the ML-II (data-informed) GP builder: lengthscales and which data set what."""

import pytest
import torch

from pigp_torch.models import ml2 as ml2_module
from pigp_torch.models import ml2_gp

BOUNDS = torch.tensor([[-1.0, -1.0], [1.0, 1.0]], dtype=torch.float64)


def _f(X):
    """Anisotropic: fast variation along knob 0, slow along knob 1."""
    return torch.sin(6.0 * X[:, 0]) + 0.5 * torch.cos(0.8 * X[:, 1])


def _data(n, seed, noise=0.01):
    g = torch.Generator().manual_seed(seed)
    X = 2 * torch.rand(n, 2, generator=g, dtype=torch.float64) - 1
    return X, _f(X) + noise * torch.randn(n, generator=g, dtype=torch.float64)


def _raw(model):
    return {n: p.detach().clone() for n, p in model.named_parameters()}


@pytest.fixture(scope="module")
def archive():
    return _data(80, seed=0)


def test_lengthscale_ordering(archive):
    """ML-II gives knob 0 (fast variation) a much shorter lengthscale than knob 1."""
    torch.manual_seed(0)
    model = ml2_gp(*archive, bounds=BOUNDS)
    ls = model.covar_module.base_kernel.lengthscale.detach().flatten()
    assert ls[0] * 3 < ls[1]
    # and the fit interpolates: residual at training points at the noise level
    resid = model.posterior(archive[0]).mean.squeeze(-1) - archive[1]
    assert resid.abs().max() < 0.1


def test_refit_false_uses_archive_hyperparameters(archive):
    """refit=False: hyperparameters equal an archive-only fit, frozen; model holds only (X, Y)."""
    X, Y = _data(6, seed=1)
    torch.manual_seed(0)
    on_archive = ml2_gp(*archive, bounds=BOUNDS)
    torch.manual_seed(0)
    model = ml2_gp(X, Y, bounds=BOUNDS, archive=archive, refit=False)
    ref = _raw(on_archive)
    got = _raw(model)
    assert ref.keys() == got.keys()
    for k in ref:
        torch.testing.assert_close(got[k], ref[k], rtol=1e-10, atol=1e-12)
    assert all(not p.requires_grad for p in model.parameters())
    assert model.train_targets.shape == (6,)
    # standardization constants are the archive's, so the noise keeps its meaning
    torch.testing.assert_close(model.outcome_transform.means, on_archive.outcome_transform.means)
    torch.testing.assert_close(model.outcome_transform.stdvs, on_archive.outcome_transform.stdvs)
    # reusing the state_dict (no fit) reproduces the same model exactly
    again = ml2_gp(X, Y, bounds=BOUNDS, refit=False, state_dict=model.state_dict())
    Xs = torch.rand(4, 2, dtype=torch.float64)
    assert torch.equal(again.posterior(Xs).mean, model.posterior(Xs).mean)


def test_refit_true_fits_on_union_and_conditions_on_current(archive):
    """refit=True with an archive: hyperparameters of a fit on archive ∪ (X, Y), data (X, Y)."""
    X, Y = _data(6, seed=2)
    torch.manual_seed(0)
    union = ml2_gp(torch.cat([archive[0], X]), torch.cat([archive[1], Y]), bounds=BOUNDS)
    torch.manual_seed(0)
    model = ml2_gp(X, Y, bounds=BOUNDS, archive=archive, refit=True)
    for k, v in _raw(union).items():
        torch.testing.assert_close(_raw(model)[k], v, rtol=1e-10, atol=1e-12)
    assert model.train_targets.shape == (6,)
    assert any(p.requires_grad for p in model.parameters())


def test_warm_start_initializes_fit_from_state_dict(archive, monkeypatch):
    """With refit, the fit starts from the state_dict's hyperparameters (not the defaults)."""
    torch.manual_seed(0)
    previous = ml2_gp(*archive, bounds=BOUNDS)
    seen = {}

    def record(mll):  # stands in for fit_gpytorch_mll: records the starting point
        seen.update(_raw(mll.model))
        return mll

    monkeypatch.setattr(ml2_module, "fit_gpytorch_mll", record)
    X, Y = _data(10, seed=4)
    ml2_gp(X, Y, bounds=BOUNDS, state_dict=previous.state_dict())
    for k, v in _raw(previous).items():
        assert torch.equal(seen[k], v), k
    cold = ml2_gp(X, Y, bounds=BOUNDS)  # without warm start: the default initial values
    ls_key = "covar_module.base_kernel.raw_lengthscale"
    assert not torch.equal(_raw(cold)[ls_key], _raw(previous)[ls_key])


def test_fixed_noise(archive):
    """With a known noise std the likelihood noise is noise^2 in standardized units, not learned."""
    torch.manual_seed(0)
    model = ml2_gp(*archive, bounds=BOUNDS, noise=0.01)
    std = model.outcome_transform.stdvs.item()
    torch.testing.assert_close(
        model.likelihood.noise, torch.full((80,), (0.01 / std) ** 2, dtype=torch.float64)
    )
    assert not any("noise" in n for n, _ in model.named_parameters())


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"refit": False}, "archive or a state_dict"),
        ({"archive": (torch.zeros(5, 3), torch.zeros(5))}, "archive X must have shape"),
        ({"archive": torch.zeros(5, 2)}, "pair"),
        ({"bounds": torch.tensor([[0.0, 1.0], [1.0, 0.0]])}, "lower bound"),
        ({"noise": -0.1}, "noise"),
        ({"refit": False, "state_dict": {}}, "lacks hyperparameters"),
    ],
)
def test_bad_inputs(kwargs, match):
    """Missing hyperparameter source, wrong shapes, bad bounds/noise/state_dict raise ValueError."""
    X, Y = _data(5, seed=3)
    kwargs = {"bounds": BOUNDS, **kwargs}
    with pytest.raises(ValueError, match=match):
        ml2_gp(X, Y, **kwargs)
