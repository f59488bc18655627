"""The online-fitted model optimizer: the regularized least-squares fit and the ask/tell loop."""

from __future__ import annotations

import pytest
import torch

from pigp_torch.optimizers.model_fit import FittedModelOptimizer, ModelFitSettings, fit_unknowns

D = torch.float64


def _linear_model(X: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    """o = (theta_0 x_0 + theta_1, theta_2 x_1): linear in the unknowns."""
    return torch.stack([theta[..., 0] * X[:, 0] + theta[..., 1], theta[..., 2] * X[:, 1]], -1)


def test_fit_matches_closed_form_for_a_linear_model():
    """For a model linear in the unknowns the Levenberg-Marquardt fit is the closed-form
    regularized least-squares solution u = (J'J/s^2 + I/sd^2)^-1 J'(o - m0)/s^2."""
    gen = torch.Generator().manual_seed(0)
    X = torch.rand(7, 2, generator=gen, dtype=D)
    c = torch.tensor([1.0, -0.5, 2.0], dtype=D)
    h = torch.tensor([0.5, 0.2, 1.0], dtype=D)
    O = _linear_model(X, torch.tensor([1.3, -0.4, 1.2], dtype=D))
    O = O + 0.01 * torch.randn(O.shape, generator=gen, dtype=D)
    s, sd = 0.01, 0.6
    u, cost = fit_unknowns(_linear_model, X, O, c, h, obs_sd=s, prior_sd=sd)
    J = torch.autograd.functional.jacobian(
        lambda v: _linear_model(X, c + h * v).reshape(-1), torch.zeros(3, dtype=D)
    )
    m0 = _linear_model(X, c).reshape(-1)
    A = J.T @ J / s**2 + torch.eye(3, dtype=D) / sd**2
    u_exact = torch.linalg.solve(A, J.T @ (O.reshape(-1) - m0) / s**2)
    torch.testing.assert_close(u, u_exact, rtol=1e-8, atol=1e-10)
    r = torch.cat([((O - _linear_model(X, c + h * u)) / s).reshape(-1), u / sd])
    assert cost == pytest.approx(float(r @ r), rel=1e-10)


def test_optimizer_finds_target_of_known_model_family():
    """With a model family that contains the machine, the optimizer drives the observables to a
    reachable target within a few readings, stays in the bounds, and needs the observables."""
    truth = torch.tensor([1.4, -0.3, 0.8], dtype=D)
    target = torch.tensor([0.5, -0.4], dtype=D)
    bounds = torch.tensor([[-1.0, -1.0], [1.0, 1.0]], dtype=D)
    opt = FittedModelOptimizer(
        bounds,
        model=_linear_model,
        goal=lambda o: ((o - target).square() + 1e-12).sqrt().mean(-1),
        theta_center=torch.tensor([1.0, 0.0, 1.0], dtype=D),
        theta_half_width=torch.tensor([0.5, 0.5, 0.5], dtype=D),
        obs_sd=1e-6,
        trust=1.0,
        maximize=False,
    )
    x = torch.zeros(2, dtype=D)
    errs = []
    for _ in range(6):
        o = _linear_model(x[None], truth)[0]
        err = float((o - target).abs().mean())
        errs.append(err)
        opt.tell(x, err, observables=o)
        x = opt.ask()
        assert ((x >= bounds[0]) & (x <= bounds[1])).all()
    assert errs[0] > 0.1 and min(errs) < 1e-4
    with pytest.raises(ValueError, match="observables"):
        opt.tell(x, 0.0)


def test_merged_repeated_readings_give_the_same_fit():
    """Readings repeated at one setting, merged into their mean counted n times, give the same
    fitted unknowns as the unmerged readings (the same least squares up to a constant)."""
    gen = torch.Generator().manual_seed(1)
    X = torch.rand(4, 2, generator=gen, dtype=D)
    rep = torch.tensor([0, 0, 0, 1, 2, 2, 3])
    truth = torch.tensor([1.2, 0.3, 0.7], dtype=D)
    O = _linear_model(X[rep], truth) + 0.05 * torch.randn(7, 2, generator=gen, dtype=D)
    c = torch.tensor([1.0, 0.0, 1.0], dtype=D)
    h = torch.tensor([0.5, 0.5, 0.5], dtype=D)
    u_all, cost_all = fit_unknowns(_linear_model, X[rep], O, c, h, obs_sd=0.05, prior_sd=0.6)
    n = torch.bincount(rep).to(D)
    mean = torch.zeros(4, 2, dtype=D).index_add_(0, rep, O) / n[:, None]
    u_m, cost_m = fit_unknowns(_linear_model, X, mean, c, h, obs_sd=0.05, prior_sd=0.6, weights=n)
    torch.testing.assert_close(u_m, u_all, rtol=1e-9, atol=1e-11)
    scatter = float(((O - mean[rep]) / 0.05).square().sum())
    assert cost_m + scatter == pytest.approx(cost_all, rel=1e-9)


def test_least_squares_in_box_finds_roots_and_stays_inside():
    """The batched projected Levenberg-Marquardt of the ask: from several starts it reaches the
    root of r(x) = (x0^2 + x1 - 1, x0 - x1) inside [0, 1]^2 (x0 = x1 = (sqrt 5 - 1) / 2); with
    the root outside a box it ends on the box edge nearest the least-squares optimum."""
    from pigp_torch.optimizers._least_squares import least_squares_in_box

    def res(X):
        return torch.stack([X[:, 0] ** 2 + X[:, 1] - 1, X[:, 0] - X[:, 1]], -1)

    box = torch.tensor([[0.0, 0.0], [1.0, 1.0]], dtype=D)
    Z0 = torch.tensor([[0.1, 0.9], [0.9, 0.1], [0.5, 0.5]], dtype=D)
    Z = least_squares_in_box(res, box, Z0, scale=1.0, max_iter=50, tol=1e-12, abs_tol=1e-24)
    root = (5**0.5 - 1) / 2
    torch.testing.assert_close(Z, torch.full_like(Z, root), atol=1e-8, rtol=0)
    small = torch.tensor([[0.0, 0.0], [0.5, 0.5]], dtype=D)
    Zs = least_squares_in_box(res, small, Z0 / 2, scale=1.0, max_iter=50)
    assert ((Zs >= 0) & (Zs <= 1)).all()
    assert float(res(Zs * 0.5).square().sum(-1).max()) < float(res(Z0 / 4).square().sum(-1).min())


def _known_family_optimizer(**kw):
    target = torch.tensor([0.5, -0.4], dtype=D)
    bounds = torch.tensor([[-1.0, -1.0], [1.0, 1.0]], dtype=D)
    opt = FittedModelOptimizer(
        bounds,
        model=_linear_model,
        goal=lambda o: ((o - target).square() + 1e-12).sqrt().mean(-1),
        residual=lambda o: o - target,
        theta_center=torch.tensor([1.0, 0.0, 1.0], dtype=D),
        theta_half_width=torch.tensor([0.5, 0.5, 0.5], dtype=D),
        maximize=False,
        **kw,
    )
    return opt, target


def test_optimizer_repeats_its_optimum_without_searching_once_the_fit_stands():
    """Noise-free, a model family containing the machine: after the fit has converged the ask
    repeats the previous optimum without a new search, the repeated readings are merged, and
    the optimum reaches the target."""
    truth = torch.tensor([1.4, -0.3, 0.8], dtype=D)
    opt, target = _known_family_optimizer(obs_sd=1e-6)
    x = torch.zeros(2, dtype=D)
    for _ in range(12):
        o = _linear_model(x[None], truth)[0]
        opt.tell(x, float((o - target).abs().mean()), observables=o)
        x = opt.ask()
    assert opt.n_reused >= 6 and opt.n_searches <= 5
    assert len(opt._merged.x) <= 6
    o = _linear_model(x[None], truth)[0]
    assert float((o - target).abs().max()) < 1e-5
    assert opt.trust == 1.0  # the readings agreed with the model: the region grew


def test_best_from_model_ignores_a_lucky_noisy_reading():
    """With best_from="model" the best setting is where the fitted model predicts the best goal,
    not the setting of the smallest noisy reading."""
    truth = torch.tensor([1.0, 0.0, 1.0], dtype=D)
    target = torch.tensor([0.5, -0.4], dtype=D)
    X = [torch.tensor([0.5, -0.4], dtype=D), torch.tensor([0.0, 0.0], dtype=D)]
    for best_from, expected in (("model", 0), ("readings", 1)):
        opt, _ = _known_family_optimizer(obs_sd=0.05, best_from=best_from)
        for i, x in enumerate(X * 3):
            o = _linear_model(x[None], truth)[0]
            y = float((o - target).abs().mean())
            opt.tell(x, y - (1.0 if (i == 1) else 0.0), observables=o)  # one lucky reading
        assert torch.equal(opt.best()[0], X[expected])


@pytest.mark.parametrize("u0", [2.2, 1.5, -1.0])
def test_a_fit_stuck_in_a_local_minimum_restarts_from_the_prior(u0):
    """o = sin(theta x) read at x = 3, 2.5, ..., 0.5 (theta = 1.3): warm-started far away
    (theta = 4 u0), the fit without restarts stays in an alias minimum with a cost above 1e5
    squared noise units; with restarts (cost above 9 per number) it finds theta = 1.3 to 1e-6
    and a cost at the noise floor."""

    def model(X, th):
        return torch.sin(th[..., :1] * X)

    results = {}
    for restarts in (0, 4):
        opt = FittedModelOptimizer(
            torch.tensor([[0.5], [3.0]], dtype=D),
            model=model,
            goal=lambda o: o.abs().sum(-1),
            theta_center=torch.tensor([0.0], dtype=D),
            theta_half_width=torch.tensor([4.0], dtype=D),
            obs_sd=1e-3,
            prior_sd=10.0,
            fit_restarts=restarts,
        )
        opt.u = torch.tensor([u0], dtype=D)
        for x in (3.0, 2.5, 2.0, 1.5, 1.0, 0.5):
            xx = torch.tensor([x], dtype=D)
            o = model(xx[None], torch.tensor([1.3], dtype=D))[0]
            opt.tell(xx, float(o.abs().sum()), observables=o)
        results[restarts] = opt
    stuck, restarted = results[0], results[4]
    assert stuck.fit_cost > 1e5 and abs(float(stuck.theta) - 1.3) > 1.0
    assert stuck.n_restarted == 0 and restarted.n_restarted >= 1
    assert float(restarted.theta) == pytest.approx(1.3, abs=1e-6)
    assert restarted.fit_cost < 0.01


def test_row_jacobian_of_a_model_for_one_vector_of_unknowns():
    """A model written for one vector of unknowns (theta[k]) cannot take a batch of them: the
    row-wise Jacobian falls back to forward mode and equals torch's Jacobian; a model that
    broadcasts (theta[..., k]) gets the batched one, equal to it as well."""
    from pigp_torch.optimizers._least_squares import row_jacobian

    X = torch.rand(5, 2, generator=torch.Generator().manual_seed(1), dtype=D)
    theta = torch.tensor([1.3, -0.4, 1.2], dtype=D)

    def one_vector(X, th):  # th[0] on a batch of unknowns is a row, not the first unknown
        return torch.stack([th[0] * X[:, 0] ** 2 + th[1], torch.sin(th[2] * X[:, 1])], -1)

    def batched(X, th):
        return torch.stack(
            [th[..., 0] * X[:, 0] ** 2 + th[..., 1], torch.sin(th[..., 2] * X[:, 1])], -1
        )

    J = torch.autograd.functional.jacobian(lambda t: batched(X, t), theta)
    for model in (one_vector, batched):
        torch.testing.assert_close(row_jacobian(model, X, theta), J, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"obs_sd": 0.0}, r"obs_sd and prior_sd must be > 0, got 0.0, "),
        ({"obs_sd": 1.0, "prior_sd": -1.0}, r"obs_sd and prior_sd must be > 0, got 1.0, -1.0"),
        ({"obs_sd": 1.0, "trust": 1.5}, r"trust must lie in \[0.01, 1.0\], got 1.5"),
        ({"obs_sd": 1.0, "fit_restarts": -1}, "fit_restarts must be >= 0, got -1"),
        (
            {"obs_sd": 1.0, "best_from": "luck"},
            "best_from must be 'readings' or 'model', got 'luck'",
        ),
    ],
)
def test_settings_are_checked_once_with_one_line_errors(options, message):
    """A ModelFitSettings out of range is refused when built (one line naming the option), and
    the optimizer built from keywords refuses the same."""
    with pytest.raises(ValueError, match=message):
        ModelFitSettings(**options)
    box = torch.tensor([[-1.0, -1.0], [1.0, 1.0]], dtype=D)
    parts = {"model": _linear_model, "goal": lambda o: o.sum(-1), "theta_center": [1.0] * 3,
             "theta_half_width": [1.0] * 3}  # fmt: skip
    with pytest.raises(ValueError, match=message):
        FittedModelOptimizer(box, **parts, **options)


def test_settings_object_and_keywords_build_the_same_optimizer():
    """``settings=`` with keywords over it gives the settings the keywords alone give; options
    nothing set are no longer accepted."""
    box = torch.tensor([[-1.0, -1.0], [1.0, 1.0]], dtype=D)
    parts = {"model": _linear_model, "goal": lambda o: o.sum(-1), "theta_center": [1.0] * 3,
             "theta_half_width": [1.0] * 3}  # fmt: skip
    base = ModelFitSettings(obs_sd=1e-3, seed=7)
    a = FittedModelOptimizer(box, settings=base, best_from="model", **parts)
    b = FittedModelOptimizer(box, obs_sd=1e-3, seed=7, best_from="model", **parts)
    assert a.settings == b.settings == ModelFitSettings(obs_sd=1e-3, seed=7, best_from="model")
    assert (a.obs_sd, a.seed, a.best_from, a.trust) == (1e-3, 7, "model", 0.25)
    with pytest.raises(TypeError, match="local_tol"):
        FittedModelOptimizer(box, obs_sd=1e-3, local_tol=0.1, **parts)


def _blurred_model(X: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    """o = sqrt((theta_0 x)^2 + theta_1^2): a size read through a screen of resolution theta_1."""
    return ((theta[..., :1] * X).square() + theta[..., 1:2].square()).sqrt()


def _unblurred(O: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    return (O.square() - theta[..., 1:2].square()).clamp_min(0.0).sqrt()


@pytest.mark.parametrize("with_beam", [False, True])
def test_the_goal_is_on_the_beam_when_the_model_names_one(with_beam):
    """With ``beam`` the ask puts the beam (the reading deblurred with the fitted resolution) on
    the target, x = t / theta_0; without it, the reading: x = sqrt(t^2 - r^2) / theta_0."""
    truth = torch.tensor([2.0, 0.3], dtype=D)
    t = 0.5
    bounds = torch.tensor([[0.0], [1.0]], dtype=D)
    opt = FittedModelOptimizer(
        bounds,
        model=_blurred_model,
        goal=lambda o: ((o[..., 0] - t).square() + 1e-14).sqrt(),
        residual=lambda o: o - t,
        beam=_unblurred if with_beam else None,
        theta_center=torch.tensor([2.0, 0.3], dtype=D),
        theta_half_width=torch.tensor([0.5, 0.2], dtype=D),
        obs_sd=1e-6,
        trust=1.0,
        maximize=False,
    )
    for x in (0.05, 0.1, 0.6, 0.9):  # sizes near and far above the resolution: r is identified
        x = torch.tensor([x], dtype=D)
        o = _blurred_model(x[None], truth)[0]
        opt.tell(x, float((o - t).abs().sum()), observables=o)
    torch.testing.assert_close(opt.theta, truth, atol=1e-6, rtol=0)
    x = float(opt.ask()[0])
    expected = t / 2.0 if with_beam else (t**2 - 0.3**2) ** 0.5 / 2.0
    assert x == pytest.approx(expected, abs=1e-6)
