"""Contract of every registered method (:data:`pigp_torch.methods.METHODS`).

For random boxes, starts, noise levels and seeds, every proposal of every method is finite and
inside the bounds; a method with a trust box (``last_info["trust_lower"/"trust_upper"]``)
proposes inside it; a step limit (``travel_limit`` of ``pigp-physics``, ``max_travel_distances``
of the Xopt methods) holds from the last told point. A newly registered method is covered
without editing this file. A method built for one task (``MethodSpec.machine``, e.g. the ARES-EA
linac's) is checked the same way on that task's simulated machine (its tuning trials 0–49).
"""

from __future__ import annotations

import importlib.util
import inspect

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pigp_torch.methods import METHODS, RunContext
from pigp_torch.prior import PhysicsPrior

DT = torch.float64
#: Cheap settings per option name, applied where a method's options accept them.
CHEAP = {"num_restarts": 2, "raw_samples": 16, "n_starts": 2, "n_restarts": 2}
HAS_XOPT = importlib.util.find_spec("xopt") is not None


class ToyMachine:
    """What the builders read of a machine: bounds, knob names, dimension."""

    def __init__(self, bounds: torch.Tensor) -> None:
        self.bounds = bounds
        self.dim = bounds.shape[1]
        self.knob_names = [f"k{i}" for i in range(self.dim)]


def _prior(bounds: torch.Tensor, x0: torch.Tensor, noise: float) -> PhysicsPrior:
    half = (bounds[1] - bounds[0]) / 2
    return PhysicsPrior(
        x0=x0, f_x0=1.0, f_inf=0.2, precision=torch.diag(4.0 / half**2), amplitude=0.2,
        noise=max(noise, 1e-3), knob_names=[f"k{i}" for i in range(bounds.shape[1])],
        bounds=bounds,
    )  # fmt: skip


def _spec(name: str, travel: float):
    spec = METHODS[name]
    names = spec.option_names() | set(spec.options)
    cheap = {k: v for k, v in CHEAP.items() if k in names}
    if name.startswith("pigp-physics"):
        cheap["travel_limit"] = travel
    return spec.with_options(**cheap)


@st.composite
def problems(draw):
    d = draw(st.integers(1, 3))
    lo = torch.tensor(draw(st.lists(st.floats(-5, 5), min_size=d, max_size=d)), dtype=DT)
    width = torch.tensor(draw(st.lists(st.floats(0.05, 10), min_size=d, max_size=d)), dtype=DT)
    u0 = torch.tensor(draw(st.lists(st.floats(0, 1), min_size=d, max_size=d)), dtype=DT)
    peak = torch.tensor(draw(st.lists(st.floats(0, 1), min_size=d, max_size=d)), dtype=DT)
    noise = draw(st.sampled_from([0.0, 0.01, 0.2]))
    travel = draw(st.floats(0.05, 0.5))
    return torch.stack([lo, lo + width]), lo + u0 * width, lo + peak * width, noise, travel


def _xopt_travel(name: str) -> float | None:
    """The per-step limit of an Xopt method (a fraction of each knob's full range), if any."""
    spec = METHODS[name]
    if not name.startswith("xopt"):
        return None
    default = inspect.signature(spec.builder).parameters["max_travel_distances"].default
    return spec.options.get("max_travel_distances", default)


def _needs_skip(name: str) -> str | None:
    if name.startswith("xopt") and not HAS_XOPT:
        return "xopt is not installed"
    return None


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(n for n in METHODS if METHODS[n].machine is None))
@settings(max_examples=4, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow])  # fmt: skip
@given(problem=problems(), seed=st.integers(0, 1000))
def test_every_method_proposes_finite_settings_in_bounds_and_limits(name, problem, seed):
    reason = _needs_skip(name)
    if reason:
        pytest.skip(reason)
    bounds, x0, peak, noise, travel = problem
    width = bounds[1] - bounds[0]
    ctx = RunContext(machine=ToyMachine(bounds), prior=_prior(bounds, peak, noise), seed=seed,
                     noise=noise if noise > 0 else None)  # fmt: skip
    opt = _spec(name, travel).build(ctx)
    xopt_travel = _xopt_travel(name)
    g = torch.Generator().manual_seed(seed)

    def f(x):
        q = (((x - peak) / width) ** 2).sum()
        return float(0.2 + 0.8 / torch.sqrt(1 + 20 * q) + noise * torch.randn((), generator=g))

    opt.tell(x0, f(x0))
    last = x0
    for _ in range(6):
        x = opt.ask()
        assert x.shape == (bounds.shape[1],) and x.dtype == DT
        assert bool(torch.isfinite(x).all())
        assert bool(((x >= bounds[0]) & (x <= bounds[1])).all())
        info = getattr(opt, "last_info", {})
        if "trust_lower" in info:
            assert bool(((x >= info["trust_lower"]) & (x <= info["trust_upper"])).all())
        if name.startswith("pigp-physics"):
            assert bool(((x - last).abs() <= travel * width / 2 * (1 + 1e-9)).all())
        if xopt_travel is not None:
            assert bool(((x - last).abs() <= xopt_travel * width * (1 + 1e-9)).all())
        opt.tell(x, f(x))
        last = x


ARES_METHODS = sorted(n for n in METHODS if METHODS[n].machine == "ares-ea")
HAS_CHEETAH = importlib.util.find_spec("cheetah") is not None


def test_every_method_names_a_known_task():
    assert {METHODS[n].machine for n in METHODS} <= {None, "ares-ea"}


@pytest.mark.slow
@pytest.mark.skipif(not HAS_CHEETAH, reason="cheetah-accelerator is not installed")
@pytest.mark.parametrize("name", ARES_METHODS)
@settings(max_examples=2, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow])  # fmt: skip
@given(trial=st.integers(0, 49), seed=st.integers(0, 1000))
def test_every_ares_method_proposes_finite_settings_in_bounds(name, trial, seed):
    """On an ARES-EA tuning trial (0–49): every proposal finite, inside the machine's bounds and
    inside a trust box the method reports."""
    from pigp_torch.machines.ares_ea.machine import AresMachine
    from pigp_torch.machines.ares_ea.simulation import load_trials

    machine = AresMachine(load_trials()[trial], seed=seed)
    bounds = machine.bounds.to(DT)
    ctx = RunContext(machine=machine, prior=None, seed=seed, maximize=machine.maximize,
                     noise=None)  # fmt: skip
    spec = METHODS[name]
    names = spec.option_names() | set(spec.options)
    opt = spec.with_options(**{k: v for k, v in CHEAP.items() if k in names}).build(ctx)
    x = machine.get().to(DT)
    for _ in range(6):
        machine.set(x)
        y = float(machine.read())
        obs = getattr(machine, "last_observables", None)
        if "observables" in inspect.signature(opt.tell).parameters:
            opt.tell(x, y, observables=obs)
        else:
            opt.tell(x, y)
        x = opt.ask()
        assert x.shape == (bounds.shape[1],) and x.dtype == DT
        assert bool(torch.isfinite(x).all())
        assert bool(((x >= bounds[0]) & (x <= bounds[1])).all())
        info = getattr(opt, "last_info", {})
        if "trust_lower" in info:
            assert bool(((x >= info["trust_lower"]) & (x <= info["trust_upper"])).all())
