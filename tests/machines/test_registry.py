"""The registry of machine kinds: what it finds, how it refuses, what each kind gives."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch

from pigp_torch.machines import KINDS, KindRegistry, MachineKind


def test_the_registry_lists_the_two_kinds_and_names_them_when_asked_for_another():
    assert sorted(KINDS) == ["ares-ea", "spear3"]
    assert KINDS.by_run_file_kind("ares-sim") is KINDS["ares-ea"]
    assert KINDS.by_run_file_kind("sim") is KINDS["spear3"]
    assert KINDS.by_run_file_kind("epics") is None
    with pytest.raises(KeyError, match=r"no machine kind 'linac'; the kinds are \['ares-ea'"):
        KINDS["linac"]


def _package(root, name: str, kinds: dict[str, str]) -> None:
    """A package ``name`` under ``root`` with one sub-package per entry (its ``__init__`` text)."""
    (root / name).mkdir()
    (root / name / "__init__.py").write_text("")
    for sub, text in kinds.items():
        (root / name / sub).mkdir()
        (root / name / sub / "__init__.py").write_text(text)


KIND_TEXT = (
    "from pigp_torch.machines import MachineKind\n"
    "class K(MachineKind):\n    name = {name!r}\nKIND = K()\n"
)


def test_a_folder_is_a_kind_and_a_folder_without_one_is_refused(tmp_path, monkeypatch):
    monkeypatch.syspath_prepend(str(tmp_path))
    _package(
        tmp_path,
        "kinds_ok",
        {"b_kind": KIND_TEXT.format(name="b"), "a": KIND_TEXT.format(name="a")},
    )
    assert list(KindRegistry("kinds_ok")) == ["a", "b"]  # in folder-name order
    _package(tmp_path, "kinds_bad", {"x": "KIND = 3\n"})
    with pytest.raises(TypeError, match=r"kinds_bad\.x defines no KIND"):
        len(KindRegistry("kinds_bad"))
    _package(
        tmp_path, "kinds_twice", {"p": KIND_TEXT.format(name="z"), "q": KIND_TEXT.format(name="z")}
    )
    with pytest.raises(TypeError, match="two machine kinds are named 'z'"):
        KindRegistry("kinds_twice")["z"]


def test_a_kinds_method_runs_on_its_own_machine_only():
    class Line(MachineKind):
        name, run_file_kind, title = "line", "line-sim", "transfer line"

    method = SimpleNamespace(name="line-physics", machine="line")
    on = SimpleNamespace(machine=SimpleNamespace(kind="line-sim"))
    off = SimpleNamespace(machine=SimpleNamespace(kind="sim"))
    Line().check_run(on, method)
    with pytest.raises(ValueError, match="line-physics is a method of the transfer line; it runs"):
        Line().check_run(off, method)
    Line().check_run(off, SimpleNamespace(name="pigp", machine=None))  # a generic method
    with pytest.raises(NotImplementedError, match="'line' has no model"):
        Line().model()


def test_each_kind_gives_its_simulator_and_its_benchmark_task():
    from pigp_torch.loop.config.sections import SECTIONS
    from pigp_torch.machines.ares_ea.benchmark import STEP_COLUMNS
    from pigp_torch.machines.ares_ea.machine import AresMachine
    from pigp_torch.machines.ares_ea.simulation import load_trials
    from pigp_torch.machines.ring.section import SimMachineConfig
    from pigp_torch.simulation import Spear3Coupling

    ring = KINDS["spear3"]
    assert ring.section() is SimMachineConfig and ring.default_method == "pigp-physics"
    assert SECTIONS["sim"] is SimMachineConfig  # the run-file schema takes it from the kind
    sim = ring.simulator(error_seed=2)
    assert isinstance(sim, Spear3Coupling) and sim.error_seed == 2
    ares = KINDS["ares-ea"]
    machine = ares.simulator(trial=7, noise=1e-6, seed=3)
    assert isinstance(machine, AresMachine) and machine.noise == 1e-6
    torch.testing.assert_close(machine.target, load_trials()[7].target.to(torch.float64))
    table = ares.benchmark(trials=[load_trials()[7]], methods=["published-nm"], steps=3)
    assert list(table.columns) == list(STEP_COLUMNS) and len(table) == 4
    assert table["trial"].tolist() == [7] * 4
