"""MachineModel: validation, the optimizer built from one, the ARES instance, and the paper's
prior from a model (closed form for a Gaussian peak)."""

from __future__ import annotations

import pytest
import torch

from pigp_torch.prior.machine_model import MachineModel, prior_from_machine_model

D = torch.float64
P = torch.tensor([[4.0, 1.0], [1.0, 2.0]], dtype=D)  # peak precision (1 / knob^2)


def _offset_model(**overrides) -> MachineModel:
    """Observables o = x - theta (a beam position that a knob moves, offset by an unknown), goal
    1 - exp(-o'Po/2): a Gaussian peak of -goal at x = theta."""

    def goal(O):
        return 1 - torch.exp(-0.5 * torch.einsum("ni,ij,nj->n", O, P, O))

    kw = dict(
        name="offset",
        knob_names=["a", "b"],
        knob_units=["A", "A"],
        bounds=torch.tensor([[-2.0, -2.0], [2.0, 2.0]], dtype=D),
        observable_names=["pos_a", "pos_b"],
        observable_units=["mm", "mm"],
        unknown_names=["off_a", "off_b"],
        unknown_units=["mm", "mm"],
        unknown_center=torch.tensor([0.3, -0.2], dtype=D),
        unknown_half_width=torch.tensor([0.5, 0.25], dtype=D),
        observe=lambda X, theta: X - theta,
        goal=goal,
        residual=lambda O: O,
    )
    kw.update(overrides)
    return MachineModel(**kw)


def test_machine_model_checks_its_description():
    m = _offset_model()
    assert m.dim == 2 and m.goal_unit == "mm"
    X = torch.tensor([[0.3, -0.2], [1.3, -0.2]], dtype=D)
    g = m.goal_at(X, m.unknown_center)
    assert float(g[0]) == 0.0 and float(g[1]) == pytest.approx(1 - torch.exp(torch.tensor(-2.0)))
    draws = m.sample_unknowns(200, seed=1)
    assert draws.shape == (200, 2)
    assert ((draws - m.unknown_center).abs() <= m.unknown_half_width).all()
    with pytest.raises(ValueError, match="half_width"):
        _offset_model(unknown_half_width=torch.tensor([0.5, 0.0], dtype=D))
    with pytest.raises(ValueError, match="unique"):
        _offset_model(knob_names=["a", "a"])
    with pytest.raises(ValueError, match="bounds"):
        _offset_model(bounds=torch.tensor([[1.0, -2.0], [-1.0, 2.0]], dtype=D))
    with pytest.raises(ValueError, match="unit"):
        _offset_model(knob_units=["A"])


def test_prior_from_machine_model_is_exact_for_a_gaussian_peak():
    """-goal = exp(-o'Po/2) - 1 with background g_inf = 1: log(f - f_inf) = -o'Po/2, so x0 = the
    unknowns' centre and the precision is P / 2 exactly; with an ensemble, center_cov is the
    covariance of the draws (each draw's optimum is the draw itself)."""
    m = _offset_model()
    prior = prior_from_machine_model(m, noise=0.01, goal_background=1.0, n_ensemble=12, seed=3)
    torch.testing.assert_close(prior.x0, m.unknown_center, atol=1e-6, rtol=0)
    torch.testing.assert_close(prior.precision, P / 2, atol=1e-5, rtol=1e-5)
    assert prior.f_inf == -1.0 and prior.knob_names == ["a", "b"]
    draws = m.sample_unknowns(12, seed=3)
    cov = torch.cov(draws.T)
    torch.testing.assert_close(prior.center_cov, cov, atol=1e-6, rtol=1e-4)
    assert prior.provenance["machine_model"] == "offset"


def test_fitted_model_optimizer_from_a_machine_model_finds_the_unknown_offset():
    """The optimizer built from the description fits the offset from two readings and asks it."""
    from pigp_torch.optimizers.model_fit import FittedModelOptimizer

    m = _offset_model()
    truth = torch.tensor([0.6, -0.4], dtype=D)
    opt = FittedModelOptimizer.from_machine_model(m, obs_sd=1e-4, trust=1.0, maximize=False)
    assert opt.machine_model is m
    x = torch.zeros(2, dtype=D)
    for _ in range(4):
        o = m.observe(x[None], truth)[0]
        opt.tell(x, float(m.goal(o[None])), observables=o)
        x = opt.ask()
    torch.testing.assert_close(x, truth, atol=1e-3, rtol=0)


def test_ares_machine_model_reproduces_the_trial_beam():
    """The ARES instance at a trial's own unknowns predicts the trial's screen beam (the energy,
    bunch length and energy spread held at the middle of their ranges do not enter the
    transverse optics) to within 1 nm, and its goal is the MAE to the target."""
    from pigp_torch.machines.ares_ea.methods import ares_machine_model
    from pigp_torch.machines.ares_ea.simulation import AresSegment, load_trials

    trial = load_trials()[3]
    m = ares_machine_model(trial.target)
    assert m.dim == 5 and len(m.unknown_names) == 19 and m.observable_units == ["m"] * 4
    assert m.unknown_names[16:] == [f"AREAMQZM{i}_gain" for i in (1, 2, 3)]
    theta = torch.cat([trial.incoming[1:9], trial.misalignments, torch.ones(3, dtype=D)])
    X = m.bounds[0] + (m.bounds[1] - m.bounds[0]) * torch.rand(
        6, 5, generator=torch.Generator().manual_seed(0), dtype=D
    )
    X = 0.2 * X  # moderate strengths: the beam stays on the screen
    o_model = m.observe(X, theta)
    o_true = AresSegment().observe(X, trial.incoming, trial.misalignments)
    torch.testing.assert_close(o_model, o_true, atol=1e-9, rtol=0)
    # without gains: the 16 unknowns of the incoming beam and misalignments, the same beam
    m16 = ares_machine_model(trial.target, quad_gain_half_width=0)
    assert len(m16.unknown_names) == 16
    torch.testing.assert_close(m16.observe(X, theta[:16]), o_true, atol=1e-9, rtol=0)
    mae = (o_true - trial.target).abs().mean(-1)
    assert (m.goal(o_true) - mae).abs().max() < 0.5e-6
