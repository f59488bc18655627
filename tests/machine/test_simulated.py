"""Tests of SimulatedMachine: noise statistics, determinism, safety refusals, noise-free values."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch

from pigp_torch.machine import Machine, SimulatedMachine

D = torch.float64
F_INF, AMP = 0.2, 1.5
X_STAR = torch.tensor([0.004, -0.003, 0.001], dtype=D)
PRECISION = torch.diag(torch.tensor([2e4, 1e4, 5e3], dtype=D))


class FakeSim:
    """Closed-form coupling model: eps_y = 1 + q, loss_rate = f_inf + A / sqrt(1 + q)."""

    knob_names = ("01G-QSS4", "02G-QSS3", "03G-QSS3")
    bounds = torch.tensor([[-0.015] * 3, [0.015] * 3], dtype=D)

    def __init__(self):
        self.n_evaluate = 0

    def evaluate(self, x):
        self.n_evaluate += 1
        x = torch.as_tensor(x, dtype=D)
        z = x - X_STAR
        q = torch.einsum("...i,ij,...j->...", z, PRECISION, z)
        return SimpleNamespace(
            eps_x=torch.ones_like(q), eps_y=1.0 + q, loss_rate=F_INF + AMP / torch.sqrt(1.0 + q)
        )


def closed_form(x):
    z = torch.as_tensor(x, dtype=D) - X_STAR
    return F_INF + AMP / torch.sqrt(1.0 + z @ PRECISION @ z)


def test_noise_statistics_over_2000_reads():
    """2000 reads at fixed knobs have std 0.04 within 5 % and mean at the noise-free value."""
    m = SimulatedMachine(FakeSim(), noise=0.04, seed=3)
    ys = torch.tensor([m.read() for _ in range(2000)], dtype=D)
    assert float(ys.std()) == pytest.approx(0.04, rel=0.05)
    assert abs(float(ys.mean()) - float(closed_form(torch.zeros(3)))) < 4 * 0.04 / 2000**0.5
    assert m.n_reads == 2000


def test_reads_are_deterministic_by_seed_and_leave_global_rng_alone():
    """Equal seeds give equal reading sequences, different seeds differ; global RNG untouched."""
    state = torch.get_rng_state()
    a = SimulatedMachine(FakeSim(), seed=5)
    b = SimulatedMachine(FakeSim(), seed=5)
    c = SimulatedMachine(FakeSim(), seed=6)
    x = torch.tensor([0.002, 0.0, -0.001], dtype=D)
    ra = [a(x) for _ in range(5)]
    assert ra == [b(x) for _ in range(5)]
    assert ra != [c(x) for _ in range(5)]
    assert torch.equal(torch.get_rng_state(), state)


def test_true_value_is_noise_free_and_side_effect_free():
    """true_value equals the closed form (single and batched) and changes no state."""
    m = SimulatedMachine(FakeSim(), seed=0)
    X = torch.tensor([[0.0, 0.0, 0.0], [0.004, -0.003, 0.001], [0.01, 0.01, -0.01]], dtype=D)
    vals = m.true_value(X)
    assert vals.shape == (3,)
    assert torch.allclose(vals, torch.stack([closed_form(x) for x in X]), rtol=1e-14)
    assert float(vals[1]) == pytest.approx(F_INF + AMP)
    assert m.true_value(X[2]).shape == ()
    assert m.n_reads == 0 and torch.equal(m.get(), torch.zeros(3, dtype=D))
    first = m.read()
    m2 = SimulatedMachine(FakeSim(), seed=0)
    m2.true_value(X)
    assert m2.read() == first  # true_value did not consume noise


def test_initial_knobs_objective_choice_and_protocol():
    """Knobs start at zero (or x_init); objective='eps_y' reads eps_y; it is a Machine."""
    sim = FakeSim()
    m = SimulatedMachine(sim, noise=0.0, objective="eps_y")
    assert isinstance(m, Machine)
    assert torch.equal(m.get(), torch.zeros(3, dtype=D))
    z = X_STAR
    assert m.read() == pytest.approx(float(1.0 + z @ PRECISION @ z))
    m2 = SimulatedMachine(sim, noise=0.0, x_init=X_STAR)
    assert torch.equal(m2.get(), X_STAR)
    assert m2.read() == pytest.approx(F_INF + AMP)
    assert m2.knob_names == list(FakeSim.knob_names)


def test_set_refuses_out_of_bounds_and_large_steps():
    """set() refuses settings outside the bounds and steps above max_step; knobs stay unchanged."""
    m = SimulatedMachine(FakeSim(), max_step=0.1)  # 0.1 of the half-range = 0.0015 per knob
    with pytest.raises(ValueError, match="outside bounds"):
        m.set(torch.tensor([0.0, 0.016, 0.0], dtype=D))
    with pytest.raises(ValueError, match="step too large"):
        m.set(torch.tensor([0.0, 0.0016, 0.0], dtype=D))
    assert torch.equal(m.get(), torch.zeros(3, dtype=D))
    m.set(torch.tensor([0.0015, -0.0015, 0.001], dtype=D))
    assert torch.equal(m.get(), torch.tensor([0.0015, -0.0015, 0.001], dtype=D))
    absolute = SimulatedMachine(FakeSim(), max_step=torch.tensor([1e-3, 1e-2, 1e-2], dtype=D))
    with pytest.raises(ValueError, match=r"knob indices \[0\]"):
        absolute(torch.tensor([0.002, 0.009, 0.0], dtype=D))
    assert absolute.n_reads == 0


def test_bad_construction_raises():
    """Negative noise, an unknown objective attribute or an incomplete sim raise ValueError."""
    with pytest.raises(ValueError, match="noise"):
        SimulatedMachine(FakeSim(), noise=-0.1)
    with pytest.raises(ValueError, match="no attribute 'emittance'"):
        SimulatedMachine(FakeSim(), objective="emittance")
    with pytest.raises(ValueError, match="evaluate"):
        SimulatedMachine(SimpleNamespace(bounds=FakeSim.bounds, knob_names=FakeSim.knob_names))
