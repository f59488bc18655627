"""pigp-physics as an Xopt generator: the same proposals as the benchmark's pigp-physics on the
same data, through Xopt's loop and a YAML dump and reload, with the trust box and step limit."""

from __future__ import annotations

from types import SimpleNamespace

import pandas as pd
import pytest
import torch
import yaml

pytest.importorskip("xopt")

from xopt import Xopt
from xopt.evaluator import Evaluator

from pigp_torch.bench import METHODS
from pigp_torch.integrations.xopt import vocs_from_prior
from pigp_torch.integrations.xopt_physics import PhysicsGenerator
from pigp_torch.prior import PhysicsPrior

DT = torch.float64
D = 4
STEPS = 6


def prior4() -> PhysicsPrior:
    g = torch.Generator().manual_seed(3)
    Q, _ = torch.linalg.qr(torch.randn(D, D, generator=g, dtype=DT))
    P = (Q * torch.tensor([1.0, 3.0, 10.0, 30.0], dtype=DT)) @ Q.T / 100.0  # 1/A^2
    return PhysicsPrior(
        x0=torch.zeros(D, dtype=DT),
        f_x0=1.5,
        f_inf=0.2,
        precision=(P + P.T) / 2,
        amplitude=0.1,
        noise=0.04,
        knob_names=["01G-QSS4", "02G-QSS3", "05G-QSS3", "07G-QSS2"],
        bounds=torch.tensor([[-30.0] * D, [30.0] * D], dtype=DT),
    )


def machine(x: torch.Tensor) -> float:
    """A deterministic peak off the centre (no noise: the same reading for the same setting)."""
    mu = torch.tensor([6.0, -4.0, 3.0, 8.0], dtype=DT)
    q = ((x - mu) ** 2 / torch.tensor([80.0, 150.0, 40.0, 200.0], dtype=DT)).sum()
    return float(0.2 + 1.3 / torch.sqrt(0.5 + q))


def native_run(prior, seed=7, steps=STEPS) -> list[torch.Tensor]:
    """The benchmark's pigp-physics (its own builder) asked and told in a plain loop."""
    ctx = SimpleNamespace(bounds=prior.bounds, prior=prior, seed=seed, noise=0.04)
    opt = METHODS["pigp-physics"].build(ctx)
    xs = [torch.zeros(D, dtype=DT)]
    opt.tell(xs[0], machine(xs[0]))
    for _ in range(steps - 1):
        x = opt.ask()
        opt.tell(x, machine(x))
        xs.append(x)
    return xs


def evaluate(names):
    def f(inputs: dict) -> dict:
        return {"loss_rate": machine(torch.tensor([inputs[n] for n in names], dtype=DT))}

    return f


@pytest.fixture(scope="module")
def native():
    return native_run(prior4())


def test_xopt_loop_proposes_what_pigp_physics_proposes(native):
    prior = prior4()
    vocs = vocs_from_prior(prior)
    gen = PhysicsGenerator(vocs=vocs, prior=prior, seed=7, noise=0.04)
    X = Xopt(generator=gen, evaluator=Evaluator(function=evaluate(prior.knob_names)))
    X.evaluate_data(pd.DataFrame([dict.fromkeys(vocs.variable_names, 0.0)]))
    for _ in range(STEPS - 1):
        X.step()
    got = torch.tensor(X.data[prior.knob_names].to_numpy(), dtype=DT)
    assert torch.allclose(got, torch.stack(native), rtol=0, atol=1e-9)
    info = X.generator.last_info
    assert {"fitted_center", "trust_lower", "trust_upper"} <= set(info)


def test_yaml_round_trip_keeps_the_prior_as_data_and_the_run_going(native):
    prior = prior4()
    vocs = vocs_from_prior(prior)
    gen = PhysicsGenerator(vocs=vocs, prior=prior, seed=7, noise=0.04)
    X = Xopt(generator=gen, evaluator=Evaluator(function=evaluate(prior.knob_names)))
    X.evaluate_data(pd.DataFrame([dict.fromkeys(vocs.variable_names, 0.0)]))
    for _ in range(STEPS - 3):
        X.step()
    text = X.yaml()
    assert "pigp_physics" in text and "precision" in text and "!!python" not in text
    config = yaml.safe_load(text)
    config.pop("evaluator")  # a local function: give it again
    # Xopt's loader: the generator by its registered name, the data replayed (set_data)
    X2 = Xopt(**config, evaluator=Evaluator(function=evaluate(prior.knob_names)))
    assert isinstance(X2.generator, PhysicsGenerator)
    assert X2.generator.optimizer.n_told == STEPS - 2 and X2.generator.replayed
    for _ in range(2):
        X2.step()
    got = torch.tensor(X2.data[prior.knob_names].to_numpy(), dtype=DT)
    # the dump keeps 10 significant digits of the data: equal up to that round-off
    assert torch.allclose(got, torch.stack(native), rtol=0, atol=1e-5)


def test_step_limit_and_trust_box_are_honoured():
    prior = prior4()
    vocs = vocs_from_prior(prior)
    gen = PhysicsGenerator(vocs=vocs, prior=prior, max_travel_distances=0.05, step_limit=0.3)
    X = Xopt(generator=gen, evaluator=Evaluator(function=evaluate(prior.knob_names)))
    X.evaluate_data(pd.DataFrame([dict.fromkeys(vocs.variable_names, 0.0)]))
    for _ in range(3):
        X.step()
    got = torch.tensor(X.data[prior.knob_names].to_numpy(), dtype=DT)
    assert float((got[1:] - got[:-1]).abs().max()) <= 0.05 * 60 + 1e-9  # 3 A per step
    assert float(got.abs().max()) <= 0.3 * 30 + 1e-9  # trust box around the best point


def test_refuses_what_the_method_cannot_do():
    prior = prior4()
    with pytest.raises(ValueError, match="MAXIMIZE"):
        PhysicsGenerator(vocs=vocs_from_prior(prior, maximize=False), prior=prior)
    gen = PhysicsGenerator(vocs=vocs_from_prior(prior), prior=prior)
    with pytest.raises(ValueError, match="one point at a time"):
        gen.generate(2)
    with pytest.raises(ValueError, match="no data yet"):
        gen.generate(1)
