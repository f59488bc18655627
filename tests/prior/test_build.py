"""Tests of prior_from_model on closed-form Gaussian objectives."""

import warnings

import pytest
import torch

from pigp_torch.prior import PhysicsPrior, prior_from_model


def test_closed_form_precision_and_optimum(bump):
    """For f = f_inf + A exp(-q/2): precision == P/2 and x0 == mu to 1e-6, amplitude A^2/12."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # an interior optimum needs neither repair nor a warning
        prior = prior_from_model(bump, bump.bounds, f_inf=bump.f_inf, noise=0.04, n_starts=4)
    assert isinstance(prior, PhysicsPrior)
    assert (prior.precision - bump.P / 2).abs().max() / (bump.P / 2).abs().max() < 1e-6
    assert (prior.x0 - bump.mu).abs().max() < 1e-6
    assert prior.f_x0 == pytest.approx(bump.f_inf + bump.A, rel=1e-12)
    assert prior.amplitude == pytest.approx(bump.A**2 / 12, rel=1e-10)
    assert prior.noise == 0.04 and prior.f_inf == bump.f_inf
    assert prior.gradient.abs().max() < 1e-3  # stationary (1/knob units; P ~ 1e4)
    assert prior.condition_number == pytest.approx(100.0, rel=1e-6)
    assert prior.provenance["build"]["repair_n_clipped"] == 0


def test_given_x0_off_optimum_warns_and_keeps_gradient(bump):
    """A non-stationary x0 warns; the gradient -P (x0 - mu) is stored, the precision unchanged."""
    x0 = bump.mu + 0.002
    with pytest.warns(RuntimeWarning, match="not a stationary point"):
        prior = prior_from_model(bump, bump.bounds, f_inf=bump.f_inf, noise=0.04, x0=x0)
    torch.testing.assert_close(prior.gradient, -bump.P @ (x0 - bump.mu), rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(prior.precision, bump.P / 2, rtol=1e-10, atol=0)
    assert prior.provenance["build"]["x0_source"] == "given"


def test_optimum_on_bound_warns(bump):
    """If the true maximum lies beyond the upper limit of knob 0, x0 sits there and it warns."""
    mu = bump.mu.clone()
    mu[0] = 0.025  # outside the +-0.015 box
    shifted = type(bump)(mu=mu, P=bump.P, A=bump.A, f_inf=bump.f_inf, bounds=bump.bounds)
    with pytest.warns(RuntimeWarning, match="not a stationary point"):
        prior = prior_from_model(shifted, bump.bounds, f_inf=0.2, noise=0.0, n_starts=4)
    assert prior.x0[0].item() == bump.bounds[1, 0].item()
    assert prior.gradient[0].item() > 1.0  # the objective still rises across the bound
    torch.testing.assert_close(prior.precision, bump.P / 2, rtol=1e-10, atol=0)


def test_amplitude_names_and_provenance_passed_through(bump):
    """Explicit amplitude, knob names and provenance end up in the prior."""
    d = bump.mu.shape[0]
    names = [f"Q{i:02d}" for i in range(d)]
    prior = prior_from_model(
        bump,
        bump.bounds,
        f_inf=0.2,
        noise=0.01,
        x0=bump.mu,
        amplitude=0.3,
        knob_names=names,
        provenance={"model": "closed form"},
    )
    assert prior.amplitude == 0.3 and prior.knob_names == names
    assert prior.provenance["model"] == "closed form"
    assert prior.provenance["build"]["newton_step"] < 1e-12


def test_saddle_is_repaired_with_warning():
    """A Hessian with a positive direction is clipped (warning) and gives a valid prior."""

    def f(X):  # log(f - 0) = -x0^2 + 0.5 x1^2: saddle at 0
        return torch.exp(-(X[:, 0] ** 2) + 0.5 * X[:, 1] ** 2)

    bounds = torch.tensor([[-1.0, -1.0], [1.0, 1.0]], dtype=torch.float64)
    with pytest.warns(RuntimeWarning, match="clipped 1 of 2"):
        prior = prior_from_model(f, bounds, f_inf=0.0, noise=0.0, x0=torch.zeros(2))
    torch.testing.assert_close(
        prior.precision, torch.diag(torch.tensor([1.0, 1e-6])).double(), rtol=1e-9, atol=1e-12
    )


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"f_inf": 5.0}, "f_inf"),
        ({"f_inf": 0.2, "knob_names": ["a"]}, "knob_names"),
        ({"f_inf": 0.2, "x0": torch.zeros(2, 4)}, "x0"),
        ({"f_inf": 0.2, "noise": -1.0}, "noise"),
    ],
)
def test_errors(bump, kwargs, match):
    """f_inf above f(x0), wrong names/x0 sizes and negative noise raise ValueError."""
    kwargs = {"noise": 0.04, "x0": bump.mu, **kwargs}
    with pytest.raises(ValueError, match=match):
        prior_from_model(bump, bump.bounds, **kwargs)


def test_non_finite_hessian_raises():
    """A kink at x0 gives a non-finite Hessian and raises ValueError."""
    bounds = torch.tensor([[-1.0, -1.0], [1.0, 1.0]], dtype=torch.float64)
    with pytest.raises(ValueError, match="not finite"):
        prior_from_model(
            lambda X: 2 - (X**2).sum(-1).sqrt(), bounds, f_inf=0.0, noise=0.0, x0=torch.zeros(2)
        )
