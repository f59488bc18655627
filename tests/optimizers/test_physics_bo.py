"""PhysicsModelBO: the prior check (misfit statistic, rejection, relaxed refit, notice)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from pigp_torch.models.inverse_sqrt import InverseSqrtPeakModel
from pigp_torch.models.physics_posterior import _extend_theta
from pigp_torch.optimizers.physics_bo import (
    BROADER_SHAPE,
    RELAXED_STAGES,
    PhysicsModelBO,
    describe_stage,
    relaxed_stages,
)
from pigp_torch.prior import PhysicsPrior

DT = torch.float64
D = 5
F_INF = 0.35
HALF = 0.015


def _prior(precision: torch.Tensor, noise: float = 0.02) -> PhysicsPrior:
    return PhysicsPrior(
        x0=torch.zeros(D, dtype=DT), f_x0=0.9, f_inf=F_INF, precision=precision, amplitude=0.1,
        noise=noise, knob_names=[f"k{i}" for i in range(D)],
        bounds=torch.tensor([[-HALF] * D, [HALF] * D], dtype=DT),
    )  # fmt: skip


def _precision(seed: int) -> torch.Tensor:
    g = np.random.default_rng(seed)
    Q, _ = np.linalg.qr(g.standard_normal((D, D)))
    P = torch.tensor(Q @ np.diag(np.geomspace(1.0, 40.0, D)) @ Q.T) / HALF**2
    return (P + P.T) / 2


def _machine(prior: PhysicsPrior, mu, c: float = 0.5):
    """A machine whose loss rate is the exact physics form of ``prior``'s shape."""
    model = InverseSqrtPeakModel(prior, prior.bounds)
    theta = torch.cat([torch.as_tensor(mu, dtype=DT), torch.tensor([math.log(c), 0.0], dtype=DT)])
    return lambda x: float(model.form(x.unsqueeze(0), theta)[0])


def _run(bo: PhysicsModelBO, f, steps: int, noise: float, seed: int = 0):
    gen = torch.Generator().manual_seed(seed)
    x = torch.zeros(D, dtype=DT)
    zs = []
    for _ in range(steps):
        bo.tell(x, f(x) + noise * float(torch.randn((), generator=gen, dtype=DT)))
        x = bo.ask()
        zs.append(bo.last_info["misfit_z"])
    return zs


MU = [0.007, -0.006, 0.004, -0.002, 0.006]


def test_a_right_prior_is_kept():
    """The machine is the prior's own physics form (other centre and depth): over 40 noisy
    readings the misfit stays near N(0, 1) and the prior is never rejected."""
    prior = _prior(_precision(0))
    bo = PhysicsModelBO(prior.bounds, prior, seed=0, n_starts=4)
    zs = _run(bo, _machine(prior, MU), 40, prior.noise)
    checked = [z for z in zs if z is not None]
    assert len(checked) >= 25  # checked from p + 5 = 12 readings on
    assert max(checked) < bo.check_z
    assert not bo.relaxed and bo.notices == []


def test_a_wrong_shape_is_rejected_once_with_a_notice_and_a_relaxed_refit():
    """The machine's shape is another random rotation of the spectrum: the misfit crosses the
    threshold, the model is rebuilt with the relaxed options (shape scales and background
    fitted), refitted with a smaller misfit, and one notice says when and why."""
    prior = _prior(_precision(0))
    machine_prior = _prior(_precision(7))
    bo = PhysicsModelBO(prior.bounds, prior, seed=0, n_starts=4)
    _run(bo, _machine(machine_prior, MU, c=0.3), 40, prior.noise)
    assert bo.relaxed
    assert len(bo.notices) == 1
    note = bo.notices[0]
    assert note["kind"] == "prior_rejected"
    assert note["z"] > bo.check_z and note["n"] >= D + 2 + 5
    assert note["at_told"] == note["n"]
    assert note["nu"] == note["n"] - (D + 2)
    assert note["z"] == pytest.approx((note["chi2"] - note["nu"]) / math.sqrt(2 * note["nu"]))
    assert "rejected after" in note["message"] and f"{note['n']} readings" in note["message"]
    last = RELAXED_STAGES[-1]
    assert bo.stage == note["stage"] == len(RELAXED_STAGES)  # a misfit goes to the last stage
    assert bo.model.shape_std == last["shape_std"]
    assert bo.model.f_inf_std == last["f_inf_std"]
    assert bo.model.log_beta_std == last["log_beta_std"]
    assert bo.model.n_params == 2 * D + 3


def test_misfit_is_the_chi_square_z_score_of_the_fitted_form():
    prior = _prior(_precision(0))
    bo = PhysicsModelBO(prior.bounds, prior, seed=0, n_starts=2)
    g = torch.Generator().manual_seed(1)
    X = (torch.rand(15, D, generator=g, dtype=DT) * 2 - 1) * HALF
    Y = F_INF + 0.3 + 0.05 * torch.rand(15, generator=g, dtype=DT)
    bo.model.fit(X, Y)
    z, chi2, nu = bo.misfit(X, Y)
    r = (Y - bo.model.form(X)) / bo.model.noise
    assert chi2 == pytest.approx(float((r**2).sum()), rel=1e-12)
    assert nu == 15 - (D + 2)
    assert z == pytest.approx((chi2 - nu) / math.sqrt(2 * nu), rel=1e-12)


def test_prior_check_off_and_validation():
    prior = _prior(_precision(0))
    bo = PhysicsModelBO(prior.bounds, prior, seed=0, n_starts=2, prior_check=False)
    _run(bo, _machine(_prior(_precision(7)), MU, c=0.3), 25, prior.noise)
    assert not bo.relaxed and bo.notices == [] and bo.last_info["misfit_z"] is None
    for bad in (0.0, -1.0, float("inf")):
        with pytest.raises(ValueError, match="check_z"):
            PhysicsModelBO(prior.bounds, prior, check_z=bad)


def test_extend_theta_keeps_the_fit_and_starts_new_parameters_at_zero():
    prior = _prior(_precision(0))
    old = InverseSqrtPeakModel(prior, prior.bounds)
    old.theta = torch.arange(D + 2, dtype=DT) / 10
    new = InverseSqrtPeakModel(prior, prior.bounds, f_inf_std=0.1, shape_std=1.0)
    out = _extend_theta(old, new)
    assert out.shape == (2 * D + 3,)
    torch.testing.assert_close(out[: D + 2], old.theta)
    assert float(out[D + 2 :].abs().max()) == 0.0


def test_center_mean_moves_the_centre_prior():
    prior = _prior(_precision(0))
    shift = torch.full((D,), 0.004, dtype=DT)
    model = InverseSqrtPeakModel(prior, prior.bounds, center_mean=shift)
    torch.testing.assert_close(model.prior_theta()[:D], shift)
    with pytest.raises(ValueError, match="center_mean"):
        InverseSqrtPeakModel(prior, prior.bounds, center_mean=[0.0, 1.0])


def test_a_wrong_scale_moves_on_by_the_evidence():
    """The machine's peak is the prior's shape 8x broader (a wrong calibration of the scale):
    the residuals can stay small, but the evidence of the stage with a free scale wins and the
    check moves there with a notice that gives the log-evidence lead."""
    prior = _prior(_precision(0))
    broad = _prior(_precision(0) / 8.0)
    bo = PhysicsModelBO(prior.bounds, prior, seed=0, n_starts=4, check_every=1)
    _run(bo, _machine(broad, [0.004, -0.003, 0.002, -0.001, 0.003], c=0.8), 40, prior.noise)
    assert bo.relaxed
    evidence = [n for n in bo.notices if n["log_evidence_ratio"] is not None]
    assert evidence and evidence[0]["log_evidence_ratio"] > bo.evidence_margin
    assert "log evidence" in evidence[0]["message"]
    assert bo.stage >= 1


def test_evidence_from_starts_the_evidence_comparison_earlier():
    """With ``evidence_from=None`` the evidence comparison waits for p + 5 readings (as the
    misfit test); ``evidence_from=k`` starts it at k readings, while the misfit test still
    waits (and no misfit z is reported before it); the default is 10."""
    prior = _prior(_precision(0))
    broad = _machine(_prior(_precision(0) / 8.0), [0.004, -0.003, 0.002, -0.001, 0.003], c=0.8)
    first = {}
    for start in (None, 4):
        bo = PhysicsModelBO(prior.bounds, prior, seed=0, n_starts=4, check_every=1,
                            evidence_from=start)  # fmt: skip
        p = bo.model.n_params
        gen = torch.Generator().manual_seed(0)
        x = torch.zeros(D, dtype=DT)
        seen, early_z = None, []
        for _ in range(p + 6):
            bo.tell(x, broad(x) + prior.noise * float(torch.randn((), generator=gen, dtype=DT)))
            x = bo.ask()
            if seen is None and bo.log_evidence_ratio is not None:
                seen = bo.n_told
            if bo.n_told < p + 5:
                early_z.append(bo.last_info["misfit_z"])
        assert early_z and all(z is None for z in early_z)
        if start is None:  # not moved before p + 5 readings, so the misfit test ran there
            assert bo.last_info["misfit_z"] is not None
        first[start] = (seen, p)
    (late_seen, p), (early_seen, _) = first[None], first[4]
    assert late_seen == p + 5
    assert early_seen == 4
    assert PhysicsModelBO(prior.bounds, prior).evidence_from == 10
    with pytest.raises(ValueError, match="evidence_from"):
        PhysicsModelBO(prior.bounds, prior, evidence_from=1)


def test_a_run_repeats_to_the_bit():
    """Two runs on the same readings choose the same settings to the last bit, through the
    evidence comparison and the relaxed stages, although the second allocates its arrays
    elsewhere (a solver whose rounding depends on memory placement would make them part)."""
    prior = _prior(_precision(0))
    f = _machine(_prior(_precision(7)), MU, c=0.3)
    padding, runs = [], []
    for repeat in range(2):
        padding.append(torch.empty(1 + 17 * repeat, dtype=DT))
        bo = PhysicsModelBO(prior.bounds, prior, seed=0, n_starts=4)
        _run(bo, f, 30, prior.noise)
        assert bo.relaxed  # the run went through a second model
        runs.append(torch.stack(bo.X).numpy())
    assert np.array_equal(runs[0], runs[1])


def test_the_first_stage_is_the_given_shape_three_times_broader_with_the_same_priors():
    """Stage 1 of the defaults: B / 3 with the given model's prior widths (no Occam cost); its
    warm start keeps the fitted curvature beta B; a bad factor is refused."""
    prior = _prior(_precision(0))
    assert RELAXED_STAGES[0] == BROADER_SHAPE == {"shape_factor": 1 / 3}
    bo = PhysicsModelBO(prior.bounds, prior, seed=0, n_starts=2)
    given = bo.model
    given.theta = torch.cat([torch.tensor(MU, dtype=DT), torch.tensor([-0.7, 0.2], dtype=DT)])
    broad = bo._stage_model(1)
    torch.testing.assert_close(broad.B, given.B / 3, rtol=1e-15, atol=0)
    assert (broad.n_params, broad.log_beta_std, broad.log_c_std, broad.f_inf_std) == (
        given.n_params, given.log_beta_std, given.log_c_std, given.f_inf_std)  # fmt: skip
    X = (torch.rand(7, D, generator=torch.Generator().manual_seed(3), dtype=DT) * 2 - 1) * HALF
    torch.testing.assert_close(broad.form(X, broad.theta), given.form(X), rtol=1e-13, atol=0)
    assert float(broad.theta[D + 1]) == pytest.approx(0.2 + math.log(3), rel=1e-13)
    for bad in (0.0, -1.0, float("nan")):
        bo = PhysicsModelBO(prior.bounds, prior, relax=[{"shape_factor": bad}])
        bo.model.theta = given.theta
        with pytest.raises(ValueError, match="shape_factor"):
            bo._stage_model(1)


def test_a_three_times_broader_peak_moves_to_the_broader_shape_at_the_first_check():
    """The machine's peak is the prior's shape 3x broader: the first evidence comparison (10
    readings on, every third ask) moves to stage 1 with a notice, and the refit there needs no
    scale far out in its prior. With the right shape the same check never moves."""
    prior = _prior(_precision(0))
    centre = [0.004, -0.003, 0.002, -0.001, 0.003]
    broad = _machine(_prior(_precision(0) / 3.0), centre, c=0.6)
    bo = PhysicsModelBO(prior.bounds, prior, seed=0, n_starts=4)
    _run(bo, broad, 20, prior.noise)
    assert bo.stage == 1 and len(bo.notices) == 1
    note = bo.notices[0]
    assert note["stage"] == 1 and note["n"] == 12  # the first check: 12 readings
    assert note["log_evidence_ratio"] > bo.evidence_margin
    assert (
        "the given shape x 0.333 (peak broader when < 1) [shape_factor = 0.333333]"
        in (note["message"])
    )
    assert abs(float(bo.model.theta[D + 1])) < 2 * bo.model.log_beta_std
    # the wide-scale stage alone (the defaults before the broader shape) leads by less at the
    # same check: it pays for its wider prior
    wide = PhysicsModelBO(prior.bounds, prior, seed=0, n_starts=4, relax=list(relaxed_stages()))
    _run(wide, broad, 12, prior.noise)
    assert wide.notices[0]["n"] == 12
    assert wide.notices[0]["log_evidence_ratio"] < note["log_evidence_ratio"] - 1.0
    right = PhysicsModelBO(prior.bounds, prior, seed=0, n_starts=4)
    _run(right, _machine(prior, centre, c=0.6), 20, prior.noise)
    assert right.stage == 0 and right.notices == []


def test_the_notice_describes_every_default_stage_in_words():
    """An operator reads the stage a run moved to in words, with the option and its value
    after them; an option without words is given as key = value."""
    texts = [describe_stage(stage) for stage in RELAXED_STAGES]
    assert texts[0] == "the given shape x 0.333 (peak broader when < 1) [shape_factor = 0.333333]"
    assert texts[1] == (
        "shape scale fitted (log std 3) [log_beta_std = 3], "
        "background fitted (relative std 0.1) [f_inf_std = 0.1]"
    )
    assert texts[2].endswith(
        "shape eigen-scales fitted (log std 1) [shape_std = 1], "
        "centre prior 4x wider in variance [center_cov_scale_factor = 4]"
    )
    assert describe_stage({"center_std": 0.5, "noise": "auto", "shape_std": "x"}) == (
        "center_std = 0.5, noise = auto, shape_std = x"
    )


def test_while_drifting_every_ask_is_the_ucb_with_track_beta():
    """Static (memory infinite): the UCB with beta = 4 alternating with the centre information;
    once the memory is finite (a drift followed) every ask is the UCB with track_beta = 1,
    whose ask lies nearer the fitted optimum (a smaller sigma at the ask than beta = 4's)."""
    prior = _prior(_precision(0))
    bo = PhysicsModelBO(prior.bounds, prior, seed=0, n_starts=4)
    _run(bo, _machine(prior, MU), 12, prior.noise)
    last = bo.parts.acquisition.last
    assert type(last).__name__ == "CentreInformation" or last.beta == 4.0
    assert not bo.parts.posterior.drifting
    betas, sds = [], {}
    for track_beta in (1.0, 4.0):
        other = PhysicsModelBO(prior.bounds, prior, seed=0, n_starts=4, track_beta=track_beta)
        _run(other, _machine(prior, MU), 12, prior.noise)
        other.parts.posterior.forgetting.tau = 50.0  # as the memory's check sets on a drift
        for _ in range(3):
            x = other.ask()
            betas.append((track_beta, other.parts.acquisition.last.beta))
        sds[track_beta] = float(other.model.predict(x.unsqueeze(0))[1][0])
    assert betas == [(1.0, 1.0)] * 3 + [(4.0, 4.0)] * 3
    assert sds[1.0] < sds[4.0]
