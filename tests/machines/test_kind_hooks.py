"""What the core asks a machine kind, through the registry only: the noise its methods and the
loop are told, the report's true curve, and its ``pigp bench`` command."""

from __future__ import annotations

import argparse
from types import SimpleNamespace

import pytest
import torch

from pigp_torch import cli
from pigp_torch.machines import KINDS, MachineKind
from pigp_torch.machines.kind import TrueObjective


def _bench_commands() -> dict[str, argparse.ArgumentParser]:
    parser = cli.build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    bench = sub.choices["bench"]
    return next(a for a in bench._actions if isinstance(a, argparse._SubParsersAction)).choices


def test_a_kind_without_hooks_adds_nothing():
    kind = MachineKind()
    assert kind.true_objective(SimpleNamespace(), print) is None
    added = []
    kind.register_bench(SimpleNamespace(add_parser=lambda *a, **k: added.append(a)))
    assert added == []
    assert kind.methods_noise(SimpleNamespace(noise=0.5)) == 0.5
    assert kind.methods_noise(SimpleNamespace(noise=0.0)) is None
    assert kind.stated_noise(SimpleNamespace(noise=0.5)) is None


def test_the_ring_tells_the_loop_its_noise_and_its_methods_none():
    """``kind: sim`` as before the registry built it: the methods keep their own noise
    defaults, the loop's re-read checks use the section's noise (mA/min)."""
    ring, ares = KINDS["spear3"], KINDS["ares-ea"]
    section = SimpleNamespace(noise=0.04)
    assert ring.methods_noise(section) is None and ring.stated_noise(section) == 0.04
    assert ring.stated_noise(SimpleNamespace(noise=0.0)) is None
    assert ares.methods_noise(section) == 0.04 and ares.stated_noise(section) is None


def test_pigp_bench_ares_comes_from_the_ares_kind(monkeypatch):
    """``pigp bench ares`` is added by ARES-EA's ``register_bench``; without it, no such
    command (the CLI names no kind)."""
    from pigp_torch.machines.ares_ea.command import cmd_bench_ares

    commands = _bench_commands()
    assert {"simulator", "bo", "ares"} <= set(commands)
    assert commands["ares"].get_default("func") is cmd_bench_ares
    monkeypatch.setattr(type(KINDS["ares-ea"]), "register_bench", lambda self, bench: None)
    assert "ares" not in _bench_commands()


@pytest.fixture(scope="module")
def sim_log(tmp_path_factory):
    """A 3-reading rcds run on the simulated ring (two knobs; the report tests' run file)."""
    from tests.test_report import write_run

    folder = tmp_path_factory.mktemp("run")
    assert cli.main(["optimize", "--config", write_run(folder, "rcds", 3), "--quiet"]) == 0
    return folder / "run.jsonl"


def test_the_reports_true_curve_is_the_kinds(sim_log, monkeypatch):
    """The report draws what the run's kind says is true (here a stand-in: the sum of the
    knobs, noise 0.5, no optimum search); with the ring's own it is the noise-free loss rate."""
    from pigp_torch.reporting.report import run_report

    ring = run_report(sim_log, fit=False)
    assert ring["noise"] == 0.04 and ring["optimum"] is not None
    assert bool((ring["true"] > 0).all()) and not torch.equal(ring["true"], ring["Y"])

    def stand_in(self, config, say):
        return TrueObjective(lambda X: X.sum(-1), noise=0.5)

    monkeypatch.setattr(type(KINDS["spear3"]), "true_objective", stand_in)
    data = run_report(sim_log, fit=False)
    assert torch.equal(data["true"], data["X"].sum(-1)) and data["noise"] == 0.5
    assert data["optimum"] is None
