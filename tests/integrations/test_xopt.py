"""Xopt integration: the physics GP built by Xopt's machinery, the ask/tell adapter, data export."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pandas as pd
import pytest
import torch

pytest.importorskip("xopt")

from xopt import Xopt
from xopt.evaluator import Evaluator
from xopt.generators.bayesian import UpperConfidenceBoundGenerator
from xopt.generators.bayesian.custom_botorch.hessian_kernel import HessianRBF
from xopt.numerical_optimizer import LBFGSOptimizer

from pigp_torch import optimize
from pigp_torch.bench import RunContext
from pigp_torch.integrations.xopt import (
    PhysicsModelConstructor,
    XoptOptimizer,
    physics_vocs_gp,
    to_xopt_dataframe,
    vocs_from_bounds,
    vocs_from_prior,
)
from pigp_torch.machine import SimulatedMachine
from pigp_torch.methods import METHODS as XOPT_METHODS
from pigp_torch.models import physics_informed_gp
from pigp_torch.prior import PhysicsPrior

DT = torch.float64
D = 13
HALF = 0.015  # 1/m, the protocol's knob box
RTOL = 1e-8
FAST_LBFGS = {"n_restarts": 2, "max_iter": 50, "max_time": None}


def synthetic_prior(d: int = D, seed: int = 0, *, asymmetric_box: bool = True) -> PhysicsPrior:
    """A prior shaped like the SPEAR3 one: condition ~500 in normalized units, ±0.015 1/m box."""
    g = torch.Generator().manual_seed(seed)
    Q, _ = torch.linalg.qr(torch.randn(d, d, generator=g, dtype=DT))
    eig = torch.logspace(0, math.log10(500.0), d, dtype=DT)
    P = (Q * eig) @ Q.T / (0.5 * HALF) ** 2
    lower = torch.full((d,), -HALF, dtype=DT)
    upper = torch.full((d,), HALF, dtype=DT)
    if asymmetric_box:  # unequal widths and an off-centre box exercise Normalize fully
        upper[0], lower[1] = 0.025, -0.005
    return PhysicsPrior(
        x0=torch.zeros(d, dtype=DT),
        f_x0=1.7,
        f_inf=0.2,
        precision=0.5 * (P + P.T),
        amplitude=(1.7 - 0.2) ** 2 / 12,
        noise=0.04,
        knob_names=[f"{i + 1:02d}G-QSS{1 + i % 4}" for i in range(d)],
        bounds=torch.stack([lower, upper]),
    )


def random_data(prior: PhysicsPrior, n: int, seed: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    """``n`` uniform points in the prior's box and a smooth objective plus noise."""
    g = torch.Generator().manual_seed(seed)
    lo, hi = prior.bounds
    X = lo + (hi - lo) * torch.rand(n, prior.dim, generator=g, dtype=DT)
    q = torch.einsum("ni,ij,nj->n", X, prior.precision, X)
    Y = 0.2 + 1.5 / torch.sqrt(1 + q) + 0.04 * torch.randn(n, generator=g, dtype=DT)
    return X, Y


def frame(prior: PhysicsPrior, X, Y, names=None, objective: str = "loss_rate") -> pd.DataFrame:
    names = prior.knob_names if names is None else names
    idx = [prior.knob_names.index(n) for n in names]
    df = pd.DataFrame(X[:, idx].numpy(), columns=names)
    df[objective] = Y.numpy()
    return df


def assert_same_posterior(model_a, model_b, X_test) -> None:
    with torch.no_grad():
        pa, pb = model_a.posterior(X_test), model_b.posterior(X_test)
    mean_a, mean_b = pa.mean.reshape(-1), pb.mean.reshape(-1)
    var_a, var_b = pa.variance.reshape(-1), pb.variance.reshape(-1)
    torch.testing.assert_close(mean_b, mean_a, rtol=RTOL, atol=0.0)
    torch.testing.assert_close(var_b, var_a, rtol=RTOL, atol=0.0)


# ----------------------------------------------------------------------------- the GP
@pytest.mark.parametrize("kernel", ["rbf", "rq"])
@pytest.mark.parametrize(
    "transform_inputs,standardize_outputs", [(True, True), (False, False), (True, False)]
)
@pytest.mark.parametrize("n", [1, 40])
def test_xopt_gp_predicts_like_physics_informed_gp(
    kernel, transform_inputs, standardize_outputs, n
):
    """Xopt's transforms are accounted for exactly: same posterior mean and variance (1e-8)."""
    prior = synthetic_prior()
    X, Y = random_data(prior, n)
    X_test, _ = random_data(prior, 64, seed=7)
    reference = physics_informed_gp(X, Y, prior, kernel=kernel)
    constructor = PhysicsModelConstructor(
        prior=prior,
        kernel=kernel,
        transform_inputs=transform_inputs,
        standardize_outputs=standardize_outputs,
    )
    model = constructor.build_model_from_vocs(vocs_from_prior(prior), frame(prior, X, Y))
    assert_same_posterior(reference, model, X_test)
    gp = model.models[0]
    assert (getattr(gp, "input_transform", None) is not None) == transform_inputs
    assert (getattr(gp, "outcome_transform", None) is not None) == standardize_outputs
    assert not any(p.requires_grad for p in gp.parameters())


def test_xopt_gp_permutes_the_precision_to_the_vocs_order():
    """A VOCS listing the knobs in another order gets the same GP (precision permuted)."""
    prior = synthetic_prior()
    X, Y = random_data(prior, 30)
    X_test, _ = random_data(prior, 32, seed=3)
    order = list(torch.randperm(D, generator=torch.Generator().manual_seed(4)).tolist())
    names = [prior.knob_names[i] for i in order]
    vocs = vocs_from_bounds(names, prior.bounds[:, order])
    model = PhysicsModelConstructor(prior=prior).build_model_from_vocs(
        vocs, frame(prior, X, Y, names)
    )
    reference = physics_informed_gp(X, Y, prior)
    with torch.no_grad():
        mean = model.posterior(X_test[:, order]).mean.reshape(-1)
        ref = reference.posterior(X_test).mean.reshape(-1)
    torch.testing.assert_close(mean, ref, rtol=RTOL, atol=0.0)


def test_generator_trains_the_physics_gp_unchanged():
    """Inside Xopt's UCB generator, train_model gives the frozen PI-GP (no hyperparameter fit)."""
    prior = synthetic_prior()
    X, Y = random_data(prior, 25)
    gen = UpperConfidenceBoundGenerator(
        vocs=vocs_from_prior(prior), gp_constructor=PhysicsModelConstructor(prior=prior)
    )
    gen.add_data(frame(prior, X, Y))
    model = gen.train_model()
    X_test, _ = random_data(prior, 16, seed=9)
    assert_same_posterior(physics_informed_gp(X, Y, prior), model, X_test)
    gp = model.models[0]
    # model coordinates: outputscale sigma_f^2 / s^2 with s the std of the data
    s = float(Y.std())
    assert float(gp.covar_module.outputscale) == pytest.approx(prior.amplitude / s**2, rel=1e-12)
    assert float(gp.mean_module.constant) == pytest.approx(
        (prior.f_inf - float(Y.mean())) / s, rel=1e-12
    )


def test_kernel_convention_stiff_direction_has_the_shorter_correlation():
    """Raw-unit prior covariance is sigma_f^2 exp(-q/2) with q = d^T Sigma d (Sigma a PRECISION)."""
    prior = synthetic_prior()
    X, Y = random_data(prior, 10)
    bounds = {n: list(v.domain) for n, v in vocs_from_prior(prior).variables.items()}
    gp = physics_vocs_gp(X, Y, prior, prior.knob_names, bounds)
    eig, vec = torch.linalg.eigh(prior.precision)
    stiff, soft = vec[:, -1], vec[:, 0]
    x = prior.x0.unsqueeze(0)
    r = 0.5 / math.sqrt(float(eig[-1]))  # half the stiff correlation length

    def k_raw(a, b):  # covariance of the model in raw units (undo Normalize and Standardize)
        with torch.no_grad():
            ta, tb = gp.input_transform(a), gp.input_transform(b)
            return (
                float(gp.covar_module(ta, tb).to_dense()) * float(gp.outcome_transform.stdvs) ** 2
            )

    k_stiff, k_soft = k_raw(x, x + r * stiff), k_raw(x, x + r * soft)
    assert k_stiff == pytest.approx(prior.amplitude * math.exp(-0.5 * r**2 * float(eig[-1])))
    assert k_soft == pytest.approx(prior.amplitude * math.exp(-0.5 * r**2 * float(eig[0])))
    assert k_stiff < 0.9 * k_soft
    # Xopt's HessianRBF given the same matrix uses its inverse as the metric: the opposite order
    hessian = HessianRBF(prior.precision).double()
    hessian.lengthscale = torch.tensor(1.0, dtype=DT)
    with torch.no_grad():
        h_stiff = float(hessian(x, x + r * stiff).to_dense())
        h_soft = float(hessian(x, x + r * soft).to_dense())
    assert h_stiff > h_soft


def test_other_outcomes_get_the_stock_xopt_gp():
    """A constraint is modelled by Xopt's standard GP next to the physics GP of the objective."""
    prior = synthetic_prior(d=2, asymmetric_box=False)
    X, Y = random_data(prior, 8)
    vocs = vocs_from_prior(prior)
    vocs.constraints = {"beam_current": ["GREATER_THAN", 0.0]}
    data = frame(prior, X, Y)
    data["beam_current"] = torch.linspace(0.1, 0.5, 8, dtype=DT).numpy()
    model = PhysicsModelConstructor(prior=prior).build_model_from_vocs(vocs, data)
    assert len(model.models) == 2
    X_test, _ = random_data(prior, 5, seed=2)
    with torch.no_grad():
        mean = model.models[0].posterior(X_test).mean
    torch.testing.assert_close(
        mean, physics_informed_gp(X, Y, prior).posterior(X_test).mean, rtol=RTOL, atol=0.0
    )
    assert any(p.requires_grad for p in model.models[1].parameters())  # trainable stock GP


def test_constructor_validates_its_inputs():
    """Clear errors: inputs that are not the prior's knobs, several outcomes, a bad prior."""
    prior = synthetic_prior(d=3, asymmetric_box=False)
    X, Y = random_data(prior, 4)
    bounds = {n: [-HALF, HALF] for n in [*prior.knob_names[:2], "other"]}
    with pytest.raises(ValueError, match="must be exactly the prior's knobs"):
        physics_vocs_gp(X, Y, prior, [*prior.knob_names[:2], "other"], bounds)
    with pytest.raises(ValueError, match="objective 'loss_rate' is not among the outcomes"):
        PhysicsModelConstructor(prior=prior, objective="loss_rate").build_model(
            prior.knob_names, ["a", "b"], frame(prior, X, Y)
        )
    with pytest.raises(ValueError, match="input_bounds are required"):
        physics_vocs_gp(X, Y, prior, prior.knob_names, None)
    with pytest.raises(ValueError, match="PhysicsPrior"):
        PhysicsModelConstructor(prior=[1, 2, 3])
    assert PhysicsModelConstructor(prior=prior.to_dict()).physics_prior.dim == 3


# ----------------------------------------------------------------------------- VOCS and data
def test_vocs_from_prior_names_and_bounds():
    """Variables named and bounded as the knobs, one MAXIMIZE (or MINIMIZE) objective."""
    prior = synthetic_prior(d=3)
    vocs = vocs_from_prior(prior, objective="loss_rate")
    assert vocs.variable_names == prior.knob_names
    assert vocs.bounds == prior.bounds.T.tolist()
    assert type(vocs.objectives["loss_rate"]).__name__ == "MaximizeObjective"
    vmin = vocs_from_prior(prior, maximize=False, objective="eps_y")
    assert type(vmin.objectives["eps_y"]).__name__ == "MinimizeObjective"
    with pytest.raises(ValueError, match="also a knob name"):
        vocs_from_prior(prior, objective=prior.knob_names[0])
    with pytest.raises(ValueError, match=r"shape \(2, 3\)"):
        vocs_from_bounds(prior.knob_names, torch.zeros(2, 4).index_fill(0, torch.tensor([1]), 1))


def test_run_log_exports_as_xopt_data_that_xopt_accepts():
    """optimize()'s table -> columns named by the VOCS; an Xopt object ingests it as data."""
    prior = synthetic_prior(d=3, asymmetric_box=False)
    vocs = vocs_from_prior(prior, constants={"energy_GeV": 3.0})
    X, Y = random_data(prior, 5)
    table = frame(prior, X, Y, objective="y")
    table.insert(0, "step", range(5))
    table["method"] = "pigp"
    table["eval_time_s"] = 0.25
    df = to_xopt_dataframe(table, vocs)
    assert list(df.columns) == [
        *prior.knob_names,
        "energy_GeV",
        "loss_rate",
        "xopt_runtime",
        "xopt_error",
    ]
    assert df.index.tolist() == list(range(5))
    torch.testing.assert_close(torch.tensor(df[prior.knob_names].to_numpy()), X)
    torch.testing.assert_close(torch.tensor(df["loss_rate"].to_numpy()), Y)
    assert (df["energy_GeV"] == 3.0).all() and (df["xopt_runtime"] == 0.25).all()
    assert not df["xopt_error"].any()

    gen = UpperConfidenceBoundGenerator(
        vocs=vocs, gp_constructor=PhysicsModelConstructor(prior=prior)
    )
    xo = Xopt(generator=gen, evaluator=Evaluator(function=lambda d: {"loss_rate": 1.0}))
    xo.add_data(df)
    assert len(xo.data) == len(xo.generator.data) == 5
    assert float(xo.data["loss_rate"].max()) == pytest.approx(float(Y.max()))

    with pytest.raises(ValueError, match="lacks knob columns"):
        to_xopt_dataframe(table.drop(columns=[prior.knob_names[1]]), vocs)
    with pytest.raises(ValueError, match="lacks output columns"):
        to_xopt_dataframe(table, vocs, objective_column="reading")
    with pytest.raises(ValueError, match="not named by the VOCS"):
        to_xopt_dataframe(table, vocs, outputs={"eps_y": "y"})


# ----------------------------------------------------------------------------- ask/tell
def _ucb(prior, **kwargs) -> UpperConfidenceBoundGenerator:
    kwargs.setdefault("gp_constructor", PhysicsModelConstructor(prior=prior))
    return UpperConfidenceBoundGenerator(
        vocs=vocs_from_prior(prior), numerical_optimizer=LBFGSOptimizer(**FAST_LBFGS), **kwargs
    )


def _objective(prior):
    P = prior.precision

    def f(x):
        return float(0.2 + 1.5 / torch.sqrt(1 + (x - 0.004) @ P @ (x - 0.004)))

    return f


def test_adapter_proposals_stay_in_bounds_and_within_the_travel_limit():
    """Driven by optimize(): every proposal is inside the VOCS box and max_travel of the last."""
    prior = synthetic_prior(d=3)
    travel = 0.1
    opt = XoptOptimizer(_ucb(prior, beta=4.0, max_travel_distances=[travel] * 3), seed=2)
    assert opt.maximize and opt.knob_names == prior.knob_names
    table = optimize(_objective(prior), opt, torch.zeros(3, dtype=DT), 7, knob_names=opt.knob_names)
    X = torch.tensor(table[prior.knob_names].to_numpy())
    lo, hi = prior.bounds
    assert bool(((X >= lo) & (X <= hi)).all())
    steps = (X[1:] - X[:-1]).abs() / (hi - lo)
    assert float(steps.max()) <= travel + 1e-9
    assert float(steps.max()) > 0.2 * travel  # it does move
    assert len(opt.generator.data) == 7 and opt.last_info["n_train"] == 6
    assert {"training", "acquisition_optimization"} <= set(opt.last_info)


def test_adapter_is_deterministic_and_leaves_the_global_rng_alone():
    """Same seed -> same proposals (stock Xopt GP, trained); torch's global RNG is untouched."""
    prior = synthetic_prior(d=2, asymmetric_box=False)
    f = _objective(prior)
    torch.manual_seed(123)
    expected = torch.rand(1).item()
    runs = []
    for _ in range(2):
        torch.manual_seed(123)
        opt = XoptOptimizer(_ucb(prior, gp_constructor=None), seed=11)
        table = optimize(f, opt, torch.zeros(2, dtype=DT), 4, knob_names=opt.knob_names)
        runs.append(table[prior.knob_names].to_numpy())
        assert torch.rand(1).item() == expected
    assert (runs[0] == runs[1]).all()


def test_adapter_minimizes_when_the_vocs_says_so_and_validates():
    """Direction from the VOCS; ask before tell and non-Xopt objects are refused."""
    prior = synthetic_prior(d=2, asymmetric_box=False)
    vocs = vocs_from_prior(prior, maximize=False)
    gen = UpperConfidenceBoundGenerator(vocs=vocs, numerical_optimizer=LBFGSOptimizer(**FAST_LBFGS))
    opt = XoptOptimizer(gen)
    assert not opt.maximize
    with pytest.raises(RuntimeError, match="tell\\(\\) the start point first"):
        opt.ask()
    opt.tell(torch.zeros(2, dtype=DT), 1.0)
    opt.tell(torch.full((2,), 0.01, dtype=DT), 0.5)
    assert opt.best()[1] == 0.5
    with pytest.raises(ValueError, match="not an Xopt generator"):
        XoptOptimizer(SimpleNamespace(vocs=vocs))


# ----------------------------------------------------------------------------- benchmark specs
class _ToyRing:
    """A cheap stand-in for Spear3Coupling: the loss rate of a correlated bowl."""

    def __init__(self, prior):
        self.prior, self.bounds, self.knob_names = prior, prior.bounds, prior.knob_names

    def evaluate(self, x):
        x = torch.as_tensor(x, dtype=DT)
        q = torch.einsum("...i,ij,...j->...", x, self.prior.precision, x)
        return SimpleNamespace(loss_rate=0.2 + 1.5 / torch.sqrt(1 + q), eps_x=q, eps_y=q)


@pytest.mark.parametrize(
    "name,beta,travel,pigp",
    [
        ("xopt-ucb", 2.0, None, False),
        ("xopt-ucb-travel", 2.0, 0.15, False),
        ("xopt-pigp", 4.0, 0.15, True),
    ],
)
def test_benchmark_specs_build_the_documented_generators(name, beta, travel, pigp):
    """The specs carry the documented Xopt settings and ask a point inside the bounds."""
    prior = synthetic_prior(d=3)
    ctx = RunContext(machine=SimulatedMachine(_ToyRing(prior), seed=1), prior=prior, seed=3)
    opt = XOPT_METHODS[name].with_options(n_restarts=2).build(ctx)
    gen = opt.generator
    assert XOPT_METHODS[name].budget == "gp"
    assert gen.beta == beta
    assert gen.max_travel_distances == (None if travel is None else [travel] * 3)
    assert gen.numerical_optimizer.max_time is None
    assert isinstance(gen.gp_constructor, PhysicsModelConstructor) == pigp
    opt.tell(torch.zeros(3, dtype=DT), float(ctx.machine.true_value(torch.zeros(3, dtype=DT))))
    x = opt.ask()
    assert bool(((x >= prior.bounds[0]) & (x <= prior.bounds[1])).all())


@pytest.mark.slow
def test_real_ring_prior_through_xopt_pigp():
    """On the 13-knob prior of the model ring: same GP through Xopt, and in-bounds proposals."""
    from pigp_torch.bench import model_prior
    from pigp_torch.simulation import Spear3Coupling

    prior = model_prior(0, n_starts=4)
    sim = Spear3Coupling(1)
    machine = SimulatedMachine(sim, noise=0.04, seed=1)
    g = torch.Generator().manual_seed(5)
    lo, hi = machine.bounds
    X = lo + (hi - lo) * torch.rand(30, sim.dim, generator=g, dtype=DT)
    Y = machine.true_value(X) + 0.04 * torch.randn(30, generator=g, dtype=DT)
    vocs = vocs_from_bounds(machine.knob_names, machine.bounds)
    model = PhysicsModelConstructor(prior=prior).build_model_from_vocs(
        vocs, frame(prior, X, Y, machine.knob_names)
    )
    X_test = lo + (hi - lo) * torch.rand(64, sim.dim, generator=g, dtype=DT)
    assert_same_posterior(physics_informed_gp(X, Y, prior), model, X_test)

    ctx = RunContext(machine=machine, prior=prior, seed=3)
    opt = XOPT_METHODS["xopt-pigp"].with_options(n_restarts=4).build(ctx)
    table = optimize(machine, opt, torch.zeros(sim.dim, dtype=DT), 5, restore="none")
    K = torch.tensor(table[machine.knob_names].to_numpy())
    assert bool(((K >= lo) & (K <= hi)).all())
    steps = (K[1:] - K[:-1]).abs() / (hi - lo)
    assert float(steps.max()) <= 0.15 + 1e-9
