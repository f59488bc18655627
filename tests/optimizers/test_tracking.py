"""The model that follows the machine: the filter against its closed form, the learned
forgetting, and the tracking optimizer on a drifting toy machine (step detection included) and
on the ring's model."""

from __future__ import annotations

import pytest
import torch

from pigp_torch.optimizers.track_filter import UnknownsFilter, information
from pigp_torch.optimizers.tracking import TrackingModelOptimizer

D = torch.float64
TARGET = torch.tensor([0.5, -0.4], dtype=D)
BOUNDS = torch.tensor([[-1.0, -1.0], [1.0, 1.0]], dtype=D)
W = torch.tensor([[1.0, 0.5, 0.0], [0.2, -1.0, 0.7]], dtype=D)


def _linear(X: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    """A model linear in its 3 unknowns: o_j = sum_k W_jk X_k theta_k (N x 3 -> N x 2)."""
    return (X[..., None, :] * W * theta[..., None, :]).sum(-1)


def _toy(X: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    """o = (theta_0 x_0 + theta_1, theta_2 x_1)."""
    return torch.stack([theta[..., 0] * X[:, 0] + theta[..., 1], theta[..., 2] * X[:, 1]], -1)


def test_the_unknowns_filter_on_a_linear_model_equals_the_batch_posterior():
    """No forgetting: the filter's estimate after N readings is the batch posterior mean
    (J^T J / s^2 + I / sigma_u^2)^-1 J^T o / s^2; the information is the batch one."""
    gen = torch.Generator().manual_seed(3)
    c, h = torch.zeros(3, dtype=D), torch.ones(3, dtype=D)
    X = torch.rand(15, 3, generator=gen, dtype=D) * 2 - 1
    O = _linear(X, torch.tensor([0.4, -0.7, 0.2], dtype=D)) + 0.05 * torch.randn(15, 2, dtype=D)
    f = UnknownsFilter(_linear, c, h, torch.zeros(3, dtype=D), obs_sd=0.1, prior_sd=0.5,
                       forgets=(1.0,))  # fmt: skip
    for x, o in zip(X, O, strict=True):
        f.update(x, o)
    J = (X[:, None, :] * W).reshape(-1, 3)
    A = J.T @ J / 0.01 + torch.eye(3, dtype=D) / 0.25
    batch = torch.linalg.solve(A, J.T @ O.reshape(-1) / 0.01)
    assert torch.allclose(f.u, batch, atol=1e-9)
    H = information(_linear, X, c, h, torch.zeros(3, dtype=D), obs_sd=0.1, prior_sd=0.5)
    assert torch.allclose(f.L[0] + f.H0, H, atol=1e-6)


@pytest.mark.parametrize("drift", [0.0, 0.02])
def test_the_forgetting_learned_is_none_on_a_static_machine_and_some_under_drift(drift):
    gen = torch.Generator().manual_seed(4)
    c, h = torch.zeros(3, dtype=D), torch.ones(3, dtype=D)
    f = UnknownsFilter(_linear, c, h, torch.zeros(3, dtype=D), obs_sd=0.01, prior_sd=1.0)
    theta = torch.tensor([0.4, -0.7, 0.2], dtype=D)
    for _ in range(150):
        theta = theta + drift * torch.tensor([1.0, 0.5, -1.0], dtype=D)
        x = torch.rand(3, generator=gen, dtype=D) * 2 - 1
        f.update(x, _linear(x[None], theta)[0] + 0.01 * torch.randn(2, generator=gen, dtype=D))
    if drift == 0:
        assert f.forget == 1.0
    else:
        # a random-walk tracker lags a linear trend by about drift / (1 - forget) (here 0.2);
        # the filter that forgets nothing is far behind
        assert f.forget < 1.0
        lag, stale = (float((u - theta).abs().max()) for u in (f.u, f.U[0]))
        assert lag < 0.3 and stale > 3 * lag, (lag, stale)


def _toy_optimizer(*, bounds=BOUNDS, model=_toy, center=(1.0, 0.0, 1.0), **kw):
    """The tracker of a toy model with 3 unknowns (half widths 0.5) for the target TARGET."""
    return TrackingModelOptimizer(
        bounds,
        model=model,
        goal=lambda o: ((o - TARGET).square() + 1e-12).sqrt().mean(-1),
        residual=lambda o: o - TARGET,
        theta_center=torch.tensor(center, dtype=D),
        theta_half_width=torch.tensor([0.5, 0.5, 0.5], dtype=D),
        obs_sd=0.001,
        maximize=False,
        **kw,
    )


def _drift_run(opt, n: int = 60, offset=lambda t: -0.2 + 0.01 * t):
    """The toy machine whose offset theta_1 is ``offset(t)`` at reading ``t`` (default a drift
    of 0.01 per reading); returns the true MAE (to the target) of each reading."""
    gen = torch.Generator().manual_seed(0)
    x, mae = torch.zeros(2, dtype=D), []
    for t in range(n):
        theta = torch.tensor([1.3, offset(t), 0.8], dtype=D)
        true = _toy(x[None], theta)[0]
        o = true + 0.001 * torch.randn(2, generator=gen, dtype=D)
        opt.tell(x, float((o - TARGET).abs().mean()), observables=o)
        mae.append(float((true - TARGET).abs().mean()))
        x = opt.ask()
    return mae


def test_a_drifting_machine_is_followed_where_the_hand_over_loses_it():
    """The offset drifts by 0.6 over 60 readings (more than its prior half width): the tracking
    optimizer keeps the median MAE of readings 30-59 under 0.01 (10 noise sd); the former
    hand-over to Nelder-Mead loses it (above 0.1); recommend() is the optimum now."""
    tracking = _toy_optimizer()
    mae = _drift_run(tracking)
    handed = _toy_optimizer(fallback="nm")
    mae_nm = _drift_run(handed)
    assert float(torch.tensor(mae[30:]).median()) < 0.01, mae[30:]
    assert float(torch.tensor(mae_nm[30:]).median()) > 0.1, mae_nm[30:]
    assert tracking.tracking and tracking.notices[0]["kind"] == "prior-check"
    assert handed.fallback is not None
    x = tracking.recommend()
    theta_now = torch.tensor([1.3, -0.2 + 0.01 * 60, 0.8], dtype=D)
    assert float((_toy(x[None], theta_now)[0] - TARGET).abs().mean()) < 0.02
    tracked = tracking.tracked()
    assert set(tracked) == {"u0", "u1", "u2", "o0_offset", "o1_offset", "x0_play", "x1_play"}
    # the tracked model (unknowns plus offset) predicts the machine of the last reading
    theta_hat = torch.tensor([tracked[f"u{i}"][0] for i in range(3)], dtype=D)
    offset = torch.tensor([tracked["o0_offset"][0], tracked["o1_offset"][0]], dtype=D)
    last = tracking.X[-1][None]
    theta_last = torch.tensor([1.3, -0.2 + 0.01 * 59, 0.8], dtype=D)
    error = (_toy(last, theta_hat)[0] + offset - _toy(last, theta_last)[0]).abs().max()
    assert float(error) < 0.01, tracked


def test_a_step_is_detected_within_two_readings_and_reacquired():
    """A static machine with quadratic terms the model lacks (the check fails, tracking starts)
    whose o0 jumps by 0.1 (100 noise sd) at reading 40: no step alarm in readings 20-40, one
    within two readings of the jump, and the MAE back under 0.01 within 8."""
    truth = torch.tensor([1.3, -0.2, 0.8], dtype=D)
    opt = _toy_optimizer(noise_probe=0)  # the timeline below: no repeat readings at the check
    gen = torch.Generator().manual_seed(0)
    x, mae = torch.zeros(2, dtype=D), []
    for t in range(55):
        true = _toy(x[None], truth)[0] + torch.stack([0.5 * x[1] ** 2, 0.4 * x[0] ** 2])
        true = true + torch.tensor([0.1 if t >= 40 else 0.0, 0.0], dtype=D)
        o = true + 0.001 * torch.randn(2, generator=gen, dtype=D)
        opt.tell(x, float((o - TARGET).abs().mean()), observables=o)
        mae.append(float((true - TARGET).abs().mean()))
        x = opt.ask()
    assert opt.tracking
    # the machine has no play, but its missing quadratic term looks like play to the first
    # check of it (reading 10): taken up, it costs one false alarm at reading 12, and its
    # learned widths go to 0 (under 1e-3 of a range of 2)
    late = [s for s in opt.steps if s > 20]
    assert late and 41 <= late[0] <= 42 and all(s <= 12 for s in opt.steps[: -len(late)]), opt.steps
    assert float(opt.play_width.max()) < 1e-3, opt.play_width
    assert any(n["kind"] == "step" for n in opt.notices)
    assert max(mae[48:]) < 0.01, mae[40:]


def test_a_machine_the_model_explains_is_tuned_as_by_the_checked_model():
    """Static toy machine in the model family: no check fails, the asks are those of the
    checked model (the tracking never starts)."""
    from pigp_torch.optimizers.model_check import CheckedModelOptimizer

    truth = torch.tensor([1.3, -0.2, 0.8], dtype=D)
    a, b = _toy_optimizer(), _toy_optimizer(fallback="nm")
    assert isinstance(b, CheckedModelOptimizer)
    gen = torch.Generator().manual_seed(0)
    x = torch.zeros(2, dtype=D)
    for _ in range(15):
        o = _toy(x[None], truth)[0] + 0.001 * torch.randn(2, generator=gen, dtype=D)
        y = float((o - TARGET).abs().mean())
        a.tell(x, y, observables=o)
        b.tell(x, y, observables=o)
        x, xb = a.ask(), b.ask()
        assert torch.equal(x, xb)
    assert not a.tracking and not a.notices
    assert torch.equal(a.recommend(), b.best()[0])


def test_the_tracking_optimizer_runs_on_the_ring_model():
    """Generic on MachineModel: the ring's model, a machine of that model whose unknowns drift;
    the tracker starts and reports the ring's unknowns and observables with their units."""
    from pigp_torch.machines import KINDS

    sim = KINDS["spear3"].simulator(error_seed=0)
    model = KINDS["spear3"].model(sim=sim)
    theta0 = model.sample_unknowns(1, seed=11)[0]
    opt = TrackingModelOptimizer.from_machine_model(
        model, obs_sd=0.01, seed=0, maximize=True, check_after=3, check_window=3,
        noise_probe=0,  # repeat readings of so fast a drift read it as noise (no tracking)
    )  # fmt: skip
    x = torch.zeros(sim.dim, dtype=D)
    # When the check first fails depends on the asks, whose round-off differs between CPUs
    # (by reading 8 on the machines of earlier runs, at 10 on an AVX-512 AMD EPYC): up to 16
    # readings, three of them tracked.
    for t in range(16):
        theta = theta0 + 0.05 * t * model.unknown_half_width
        with torch.no_grad():
            o = model.observe(x[None], theta)[0]
        opt.tell(x, float(-model.goal(o[None])[0]), observables=o)
        x = opt.ask()
        assert bool(((x >= opt.bounds[0]) & (x <= opt.bounds[1])).all())
        if opt.n_tracked >= 3:
            break
    assert opt.tracking and opt.n_tracked == 3
    tracked = opt.tracked()
    for name, unit in zip(model.unknown_names, model.unknown_units, strict=True):
        assert tracked[name][1] == unit
    for name, unit in zip(model.observable_names, model.observable_units, strict=True):
        assert tracked[f"{name}_offset"][1] == unit


def test_ares_physics_tracks_by_default_and_hands_over_as_an_option():
    """The default of ares-physics follows the machine (docs/drift_families.md), with the play
    of every magnet modelled; ``fallback="nm"`` gives the former hand-over to Nelder-Mead."""
    from pigp_torch.machines import KINDS
    from pigp_torch.methods import METHODS, RunContext

    machine = KINDS["ares-ea"].simulator(trial=3, objective="mae")
    ctx = RunContext(machine=machine, noise=None, maximize=False)
    opt = METHODS["ares-physics"].build(ctx)
    assert isinstance(opt, TrackingModelOptimizer) and opt.track
    assert opt.offset_half_width == pytest.approx(50e-6)  # 50 x the 1 um noise floor
    assert torch.allclose(opt._play_half, 0.005 * (opt.bounds[1] - opt.bounds[0]))
    handing = METHODS["ares-physics"].with_options(fallback="nm").build(ctx)
    assert not handing.track
