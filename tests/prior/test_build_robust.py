"""prior_from_model on models that are not ours: a peak hidden in a wide box, flat models."""

import warnings

import pytest
import torch

from pigp_torch.prior import prior_from_model

D = 13
F_INF, A = 0.3, 1.2
BOX = torch.tensor([[-1.0] * D, [1.0] * D], dtype=torch.float64)


def wide_bump(seed: int, centre_offset: float = 0.1):
    """f = 0.3 + 1.2 exp(-d^T P d / 2), d = x - c, P eigenvalues 1 ... 100 (linear, random
    orientation), c within +-centre_offset of the middle of the +-1 box; returns (f, P, c)."""
    g = torch.Generator().manual_seed(seed)
    Q, _ = torch.linalg.qr(torch.randn(D, D, generator=g, dtype=torch.float64))
    P = Q @ torch.diag(torch.linspace(1.0, 100.0, D, dtype=torch.float64)) @ Q.T
    P = 0.5 * (P + P.T)
    c = centre_offset * (2 * torch.rand(D, generator=g, dtype=torch.float64) - 1)

    def f(X):
        delta = X - c
        return F_INF + A * torch.exp(-0.5 * ((delta @ P) * delta).sum(-1))

    return f, P, c


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_wide_box_bump_found_with_closed_form_precision(seed):
    """The search finds the peak of a 13-D bump whose tails underflow on most of the box:
    x0 = c, f(x0) = 1.5 and precision = P / 2 (closed form), without warnings."""
    f, P, c = wide_bump(seed)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        prior = prior_from_model(f, BOX, f_inf=F_INF, noise=0.0, seed=seed)
    assert (prior.x0 - c).abs().max().item() < 1e-6
    assert prior.f_x0 == pytest.approx(F_INF + A, rel=1e-12)
    rel = ((prior.precision - P / 2).abs().max() / (P / 2).abs().max()).item()
    assert rel < 1e-6
    build = prior.provenance["build"]
    assert build["x0_source"] == "search" and build["knobs_on_bound"] == []
    assert build["repair_n_clipped"] == 0 and build["newton_step"] < 1e-3


def test_without_samples_the_wide_bump_is_rejected_not_returned():
    """With only 2 Sobol starts and no samples the peak is missed, and a ValueError says so
    (value at x0, best sample, f_inf, what to do) instead of returning a background point."""
    f, _, _ = wide_bump(0)
    with pytest.raises(ValueError, match="did not find a maximum") as err:
        prior_from_model(f, BOX, f_inf=F_INF, noise=0.0, n_starts=2, n_samples=0)
    msg = str(err.value)
    assert "f_inf = 0.3" in msg and "best of 2 sampled points" in msg
    assert "n_samples" in msg and "x_init" in msg and "give x0" in msg


def test_x_init_near_the_peak_is_enough():
    """A single start near the peak (x_init, no Sobol points) finds it: x0 = c to 1e-6."""
    f, P, c = wide_bump(1)
    prior = prior_from_model(
        f, BOX, f_inf=F_INF, noise=0.0, n_starts=0, n_samples=0, x_init=c + 0.05
    )
    assert (prior.x0 - c).abs().max().item() < 1e-6
    torch.testing.assert_close(prior.precision, P / 2, rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize(
    ("f", "match"),
    [
        (lambda X: torch.full((X.shape[0],), 0.7, dtype=torch.float64), "flat"),
        (lambda X: 0.7 + 0.0 * X.sum(-1), "flat"),
        (lambda X: F_INF - (X**2).sum(-1), "does not rise above the background"),
        (lambda X: F_INF + 1e-12 * torch.exp(-(X**2).sum(-1)), "flat background"),
    ],
    ids=["constant", "constant-with-graph", "below-f_inf", "negligible-excess"],
)
def test_flat_model_raises(f, match):
    """A constant model, one never above f_inf, or one with a negligible excess raises a
    ValueError that names the problem and f_inf instead of returning a prior."""
    b = BOX[:, :3]
    with pytest.raises(ValueError, match=match) as err:
        prior_from_model(f, b, f_inf=F_INF, noise=0.0, n_samples=256)
    assert "f_inf = 0.3" in str(err.value)


def test_minimum_is_rejected():
    """A search that ends at a minimum (its only start sits on the zero gradient of a dip) raises
    a ValueError naming the positive curvature instead of returning the minimum."""

    def f(X):  # log(f - 0) = |x|^2: minimum at 0, maxima in the corners
        return torch.exp((X**2).sum(-1))

    b = BOX[:, :2]
    with pytest.raises(ValueError, match="positive eigenvalue"):
        prior_from_model(f, b, f_inf=0.0, noise=0.0, n_starts=0, n_samples=0, x_init=[0.0, 0.0])


def test_centre_outside_box_gives_bound_with_warning():
    """A peak beyond the upper limit of knobs 0 and 5 gives x0 on those bounds with a warning
    (no error); the free knobs sit at the constrained maximum (zero free gradient) and the
    precision is still P / 2."""
    _, P, c = wide_bump(2)
    c_out = c.clone()
    c_out[0], c_out[5] = 1.3, 1.2

    def f(X):
        delta = X - c_out
        return F_INF + A * torch.exp(-0.5 * ((delta @ P) * delta).sum(-1))

    with pytest.warns(RuntimeWarning, match=r"not a stationary point.*lie on a bound"):
        prior = prior_from_model(f, BOX, f_inf=F_INF, noise=0.0)
    on_bound = prior.provenance["build"]["knobs_on_bound"]
    assert set(on_bound) <= {"x0", "x5"} and "x0" in on_bound
    idx = [int(name[1:]) for name in on_bound]
    assert all(prior.x0[i].item() == 1.0 for i in idx)
    free = [i for i in range(D) if i not in idx]
    assert prior.gradient[free].abs().max().item() < 1e-6
    assert (prior.gradient[idx] > 0.1).all()
    torch.testing.assert_close(prior.precision, P / 2, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"n_samples": -1}, "n_samples"),
        ({"n_sample_starts": -2}, "n_sample_starts"),
        ({"n_starts": 0, "n_samples": 0}, "no starting point"),
        ({"x_init": torch.zeros(4)}, "x_init"),
    ],
)
def test_bad_search_arguments(kwargs, match):
    """Negative sample counts, no start at all, or a wrong-size x_init raise ValueError."""
    f, _, _ = wide_bump(0)
    with pytest.raises(ValueError, match=match):
        prior_from_model(f, BOX, f_inf=F_INF, noise=0.0, **kwargs)
