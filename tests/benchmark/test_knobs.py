"""Tests of the benchmark's knob selection: machines, prior and f* all use the same knobs."""

import pytest
import torch

from pigp_torch.bench import METHODS, machine_optimum, model_prior, run_benchmark, run_one
from pigp_torch.simulation import Spear3Coupling

#: Three windings of the ring (cheap 3-D problems: prior and f* in about a second).
THREE = ["01G-QSS4", "05G-QSS2", "11G-QSS3"]


@pytest.fixture(scope="module")
def prior3():
    return model_prior(0, n_starts=2, knobs=THREE)


def test_three_knob_benchmark_uses_those_knobs(prior3):
    """A run on 3 chosen windings: knob columns, noise-free values and f* of the 3-knob
    machine (not the 13-knob one)."""
    assert prior3.knob_names == THREE
    df = run_benchmark(
        ["nelder-mead"],
        [1],
        budgets={"direct": 5},
        prior=prior3,
        knobs=THREE,
        progress=False,
        optimum_starts=2,
    )
    assert list(df.columns[3:6]) == THREE and "01G-QSS1" not in df.columns
    from pigp_torch.bench.protocol import machine_loss_map

    model = Spear3Coupling(1, knobs=THREE)
    sim = Spear3Coupling(1, knobs=THREE, loss_rate_map=machine_loss_map(1, model.loss_rate_map))
    X = torch.tensor(df[THREE].to_numpy(), dtype=torch.float64)
    assert df["f_true"].to_numpy() == pytest.approx(sim.loss_rate(X).detach().numpy(), rel=1e-12)
    f_star3 = machine_optimum(1, 2, knobs=THREE, machine_maps=True)
    assert df["f_star"].unique().tolist() == [f_star3]
    assert f_star3 == pytest.approx(sim.optimum(n_starts=2)[1], rel=1e-12)
    assert machine_optimum(1, 2, knobs=THREE[:2], machine_maps=True) < f_star3  # per knob set
    assert f_star3 >= df["f_true"].max()


def test_prior_for_other_knobs_is_refused(prior3):
    """A 3-knob prior cannot drive the 13- or 72-knob machines (run_benchmark and run_one)."""
    with pytest.raises(ValueError, match=r"the prior is for 3 knobs, the machines have 72"):
        run_benchmark(["pigp"], [1], knobs="all72", progress=False, prior=prior3)
    with pytest.raises(ValueError, match=r"the prior is for 3 knobs .* the machines have 13"):
        run_one(METHODS["pigp"], 1, prior3, budget=2)
    with pytest.raises(ValueError, match="unknown knob set 'all73'"):
        run_benchmark(["pigp"], [1], knobs="all73", progress=False, prior=prior3)


def test_model_prior_with_center_ensemble_on_three_knobs():
    """``center_ensemble=n`` adds the second moment of the optima of the n rings 1001... (here
    3-knob rings, so 4 rings suffice for a full-rank 3 x 3 matrix) and their mean peak shape,
    with provenance."""
    from pigp_torch.simulation.ensemble import ensemble_optima

    p = model_prior(0, n_starts=2, knobs=THREE, center_ensemble=4)
    optima = ensemble_optima([1001, 1002, 1003, 1004], knobs=THREE)
    X = optima.centers
    assert optima.seeds == [1001, 1002, 1003, 1004]
    torch.testing.assert_close(p.center_cov, X.T @ X / 4, rtol=1e-12, atol=0)
    torch.testing.assert_close(p.peak_shape, optima.shapes.mean(0), rtol=1e-12, atol=0)
    assert p.provenance["center_ensemble_seeds"] == [1001, 1004, 4]
    alone = model_prior(0, n_starts=2, knobs=THREE)
    assert alone.center_cov is None and alone.peak_shape is None


def test_run_benchmark_builds_the_ensemble_only_for_methods_that_use_it(monkeypatch):
    """Machine seeds may not be ensemble seeds (checked before any work), and methods that do
    not read ``center_cov`` never pay for the ensemble."""
    import pigp_torch.bench.protocol as protocol

    with pytest.raises(ValueError, match=r"machine seeds \[1002\] are also ensemble seeds"):
        run_benchmark(["pigp-physics"], [1002], progress=False, center_ensemble=3, knobs=THREE)

    def forbidden(*args, **kwargs):
        raise AssertionError("the ensemble was computed for a method that does not use it")

    monkeypatch.setattr(protocol, "ensemble_optima", forbidden)
    df = run_benchmark(
        ["nelder-mead"], [1002], budgets={"direct": 3}, progress=False, knobs=THREE,
        optimum_starts=0, center_ensemble=3,
    )  # fmt: skip
    assert len(df) == 3
    assert METHODS["pigp-physics"].uses_center_ensemble
    assert not METHODS["pigp-physics-box"].uses_center_ensemble
