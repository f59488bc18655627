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
