"""The method registry: one entry per method, read by run files, the benchmark and the CLI."""

from __future__ import annotations

import pytest
import torch

from pigp_torch.bench import METHODS as BENCHMARK_METHODS
from pigp_torch.methods import (
    METHODS,
    MethodSpec,
    RunContext,
    build_nelder_mead,
    method_options,
    register,
    run_file_methods,
)
from pigp_torch.methods import registry as registry_module
from pigp_torch.optimizers import RCDS, NelderMead

D = torch.float64
BOUNDS = torch.tensor([[-1.0, -2.0], [1.0, 2.0]], dtype=D)


def test_run_files_accept_the_nine_methods_in_their_order():
    """The six of any ring, then the three of the ARES-EA linac (machine kind: ares-sim)."""
    ring = ("pigp", "pigp-fast", "pigp-physics", "ml2", "nelder-mead", "rcds")
    assert run_file_methods() == (*ring, "published-bo", "published-nm", "ares-physics")
    assert {METHODS[n].machine for n in run_file_methods()} == {None, "ares-ea"}


def test_every_method_name_is_known_to_the_benchmark():
    names = {"pigp", "pigp-zero-mean", "pigp-physics", "pigp-physics-box"}
    names |= {"pigp-fast", "ml2", "nelder-mead", "rcds", "xopt-ucb", "xopt-ucb-travel"}
    names |= {"xopt-pigp"}
    names |= {"published-bo", "published-nm", "ares-physics"}  # the ARES-EA linac's methods
    assert set(METHODS) == names
    assert BENCHMARK_METHODS is METHODS  # one registry, no second copy
    assert {"pigp-zero-mean", "pigp-physics-box"}.isdisjoint(run_file_methods())


def test_run_file_options_come_from_the_builders_signatures():
    assert method_options("rcds") == {"noise", "step", "directions"}
    assert method_options("nelder-mead") == {"initial_simplex_size", "adaptive", "xatol", "fatol"}
    ml2 = method_options("ml2")
    assert {"refit_every", "noise", "beta", "step_limit"} <= ml2
    assert ml2.isdisjoint({"archive_spread", "learn_noise", "model", "seed", "maximize"})
    with pytest.raises(ValueError, match="unknown method 'xopt-ucb'"):
        method_options("xopt-ucb")  # a benchmark method, not one of the run files


def test_a_new_method_is_one_entry(monkeypatch):
    monkeypatch.setattr(registry_module, "METHODS", dict(METHODS))
    spec = register(
        MethodSpec("nm-wide", build_nelder_mead, "direct", {"initial_simplex_size": 0.3},
                   run_file=True, forwards_to=(NelderMead,))
    )  # fmt: skip
    assert registry_module.run_file_methods()[-1] == "nm-wide"
    assert "xatol" in registry_module.method_options("nm-wide")
    opt = spec.build(RunContext(knob_bounds=BOUNDS, noise=None, archive_size=0))
    assert isinstance(opt, NelderMead) and opt.initial_simplex_size == 0.3
    with pytest.raises(ValueError, match="registered already"):
        register(spec)


def test_the_context_decides_what_the_run_file_and_the_benchmark_give():
    """A run file knows no noise level (RCDS keeps its own default, 0); the benchmark passes the
    machine's; the direction comes from the context."""
    run_file = METHODS["rcds"].build(
        RunContext(knob_bounds=BOUNDS, noise=None, archive_size=0, maximize=False)
    )
    bench = METHODS["rcds"].build(RunContext(knob_bounds=BOUNDS, noise=0.04))
    assert isinstance(run_file, RCDS) and run_file.noise == 0.0 and not run_file.maximize
    assert bench.noise == 0.04 and bench.maximize


def test_ml2_without_an_archive_must_refit():
    ctx = RunContext(knob_bounds=BOUNDS, noise=None, archive_size=0)
    with pytest.raises(ValueError, match="no archive to fit once"):
        METHODS["ml2"].with_options(refit_every=0).build(ctx)
