"""The prior check of the fitted model: silent on the right model, a fallback on a wrong one."""

from __future__ import annotations

import pytest
import torch

from pigp_torch.optimizers.model_check import CheckedModelOptimizer, chi2_check

D = torch.float64
TARGET = torch.tensor([0.5, -0.4], dtype=D)
BOUNDS = torch.tensor([[-1.0, -1.0], [1.0, 1.0]], dtype=D)


def _model(X: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    """o = (theta_0 x_0 + theta_1, theta_2 x_1)."""
    return torch.stack([theta[..., 0] * X[:, 0] + theta[..., 1], theta[..., 2] * X[:, 1]], -1)


def _optimizer(sd: float, **kw) -> CheckedModelOptimizer:
    return CheckedModelOptimizer(
        BOUNDS,
        model=_model,
        goal=lambda o: ((o - TARGET).square() + 1e-12).sqrt().mean(-1),
        residual=lambda o: o - TARGET,
        theta_center=torch.tensor([1.0, 0.0, 1.0], dtype=D),
        theta_half_width=torch.tensor([0.5, 0.5, 0.5], dtype=D),
        obs_sd=sd,
        maximize=False,
        **kw,
    )


def _run(opt, machine, sd: float, n: int, seed: int = 0):
    gen = torch.Generator().manual_seed(seed)
    x = torch.zeros(2, dtype=D)
    for _ in range(n):
        o = machine(x) + sd * torch.randn(2, generator=gen, dtype=D)
        opt.tell(x, float((o - TARGET).abs().mean()), observables=o)
        x = opt.ask()
    return x


def test_chi2_check_matches_its_closed_form():
    X = torch.tensor([[0.1, 0.2], [0.3, -0.4]], dtype=D)
    theta = torch.tensor([1.0, 0.0, 1.0], dtype=D)
    O = _model(X, theta) + torch.tensor([[0.1, -0.2], [0.0, 0.3]], dtype=D)
    chi2, dof, p = chi2_check(_model, X, O, theta, 0.1)
    assert chi2 == pytest.approx(1 + 4 + 0 + 9) and dof == 4
    from scipy.stats import chi2 as dist

    assert p == pytest.approx(dist.sf(14.0, 4))


@pytest.mark.parametrize("seed", [0, 1])
def test_right_model_with_noise_never_falls_back(seed):
    """The machine is in the model family, noise as stated: 25 readings, no fallback, every
    check's chi2 within its plausible range."""
    truth = torch.tensor([1.3, -0.2, 0.8], dtype=D)
    opt = _optimizer(0.01, fallback="nm")
    _run(opt, lambda x: _model(x[None], truth)[0], 0.01, 25, seed)
    assert opt.fallback is None and not opt.notices
    assert len(opt.checks) == 21 and min(c["p"] for c in opt.checks) > 1e-4


def test_wrong_model_falls_back_with_a_notice_and_the_fallback_asks():
    """The machine has a quadratic term the model lacks: the check fails twice in a row, a
    notice says so, the asks then come from the model-free search and the best setting is the
    best reading."""
    truth = torch.tensor([1.3, -0.2, 0.8], dtype=D)

    def machine(x):
        return _model(x[None], truth)[0] + torch.stack([0.5 * x[1] ** 2, 0.4 * x[0] ** 2])

    opt = _optimizer(0.001, fallback="nm")
    _run(opt, machine, 0.001, 30)
    assert opt.fallback is not None
    (notice,) = opt.notices
    assert notice["kind"] == "prior-check" and notice["p"] < opt.check_alpha
    assert "model-free" in notice["message"]
    fell = notice["at_told"]
    assert 5 <= fell <= 15
    assert opt.fallback.n_told == opt.n_told - fell + 1  # the best reading, then the rest
    assert opt.best()[1] == min(opt.Y)
    with pytest.raises(ValueError, match="fallback"):
        _optimizer(0.01, fallback="nope")


def _noisy_runs(truth_machine, stated: float, sd: float, seeds, n: int = 30, **kw):
    """One optimizer per seed, ``n`` readings with noise ``sd`` against the stated ``stated``."""
    out = []
    for seed in seeds:
        opt = _optimizer(stated, fallback="nm", **kw)
        _run(opt, truth_machine, sd, n, seed)
        out.append(opt)
    return out


def test_the_noise_probe_learns_the_noise_and_keeps_the_right_model():
    """The right model, readings 5x noisier than stated (jitter the stated noise lacks), 10
    seeds of 30 readings: without the probe every run hands over; with it at most 1 in 10 does
    (a false-alarm rate of at most 10 %), the learned noise is within 0.5-1.5x the true 0.01, and
    the recommended setting is nearer the optimum than the best reading on average."""
    truth = torch.tensor([1.3, -0.2, 0.8], dtype=D)

    def machine(x):
        return _model(x[None], truth)[0]

    x_opt = torch.stack([(TARGET[0] - truth[1]) / truth[0], TARGET[1] / truth[2]])
    plain = _noisy_runs(machine, 0.002, 0.01, range(10), noise_probe=0)
    assert all(o.fallback is not None for o in plain)
    probed = _noisy_runs(machine, 0.002, 0.01, range(10))
    assert sum(o.fallback is not None for o in probed) <= 1
    for o in probed:
        assert 0.005 <= o.noise_sd <= 0.015 and o.best_from == "model"
        assert o.obs_sd == o.noise_sd and o.check_sd > o.noise_sd
    d_rec = [float((o.recommend() - x_opt).norm()) for o in probed]
    d_best = [float((o.X[int(torch.tensor(o.Y).argmin())] - x_opt).norm()) for o in probed]
    assert sum(d_rec) < 0.8 * sum(d_best)


def test_the_noise_probe_on_a_deterministic_machine_hands_over_as_before():
    """A wrong model without noise: the probe's one repeat reads the same to the bit, so the
    check hands over at the same reading as without the probe; the recommended setting is the
    best reading."""
    truth = torch.tensor([1.3, -0.2, 0.8], dtype=D)

    def machine(x):
        return _model(x[None], truth)[0] + torch.stack([0.5 * x[1] ** 2, 0.4 * x[0] ** 2])

    (plain,) = _noisy_runs(machine, 0.001, 0.0, [0], noise_probe=0)
    (probed,) = _noisy_runs(machine, 0.001, 0.0, [0])
    fell = probed.notices[0]["at_told"]
    assert fell == plain.notices[0]["at_told"]
    assert torch.equal(probed.X[fell - 1], probed.X[fell - 2])  # the repeat reading
    assert probed.noise_sd == 0.0 and probed.check_sd == probed.obs_sd == 0.001
    assert probed.best_from == "readings"
    assert torch.equal(probed.recommend(), probed.X[int(torch.tensor(probed.Y).argmin())])
    with pytest.raises(ValueError, match="noise_probe"):
        _optimizer(0.01, noise_probe=-1)
