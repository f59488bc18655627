"""The public names that moved into a kind's folder (ARES-EA's, the ring's) still import from
their old paths, as the same objects; the data files moved with them load from their new place."""

from __future__ import annotations

import importlib
from pathlib import Path

import pytest

MOVED = {
    "pigp_torch.machine.ares": "pigp_torch.machines.ares_ea.machine",
    "pigp_torch.benchmark.ares": "pigp_torch.machines.ares_ea.benchmark",
    "pigp_torch.simulation.ares": "pigp_torch.machines.ares_ea.simulation",
    "pigp_torch.commands.bench_ares": "pigp_torch.machines.ares_ea.command",
}
#: The ring's simulation modules, moved from ``pigp_torch/simulation`` by ``git mv``.
RING_MODULES = (
    "calibration deck ensemble errors lattice linear_model lyapunov reference ring spear3 spec "
    "throughput"
).split()


@pytest.mark.parametrize(("old", "new"), sorted(MOVED.items()))
def test_an_old_path_re_exports_the_moved_names(old, new):
    alias, module = importlib.import_module(old), importlib.import_module(new)
    assert alias.__all__
    for name in alias.__all__:
        assert getattr(alias, name) is getattr(module, name), name


@pytest.mark.parametrize("name", RING_MODULES)
def test_an_old_ring_module_path_is_the_moved_module(name):
    """``pigp_torch.simulation.<m>`` is ``pigp_torch.machines.ring.<m>`` itself (one module:
    its state and a monkeypatch are shared)."""
    old = importlib.import_module(f"pigp_torch.simulation.{name}")
    assert old is importlib.import_module(f"pigp_torch.machines.ring.{name}")
    assert old.__spec__.name == f"pigp_torch.machines.ring.{name}"


def test_the_names_outside_checks_call_are_there():
    from pigp_torch.benchmark.ares import run_ares_benchmark, run_ares_trial, score_runs
    from pigp_torch.machine.ares import AresMachine
    from pigp_torch.methods import METHODS, RunContext

    assert AresMachine.__module__ == "pigp_torch.machines.ares_ea.machine"
    assert {"published-bo", "published-nm", "ares-physics"} <= set(METHODS)
    assert METHODS["ares-physics"].machine == "ares-ea"
    assert callable(run_ares_benchmark) and callable(run_ares_trial) and callable(score_runs)
    assert RunContext().seed == 0


def test_the_ring_package_path_re_exports_the_rings_entry_points():
    """``pigp_torch.simulation.Spear3Coupling`` (DESIGN's public name) and the rest of the old
    package's names are the ring kind's objects."""
    import pigp_torch.simulation as old
    from pigp_torch.machines.ring import calibration, lattice, ring, spear3

    assert old.Spear3Coupling is spear3.Spear3Coupling
    assert old.RingCoupling is ring.RingCoupling and old.load_ring is lattice.load_ring
    assert old.calibrate_loss_rate_map is calibration.calibrate_loss_rate_map
    assert set(old.__all__) == {
        "LOSS_RATE_MAP", "SKEW_K_PER_A_M2", "TARGET_RATIO", "CouplingResult", "RingCoupling",
        "Spear3Coupling", "calibrate_loss_rate_map", "load_ring",
    }  # fmt: skip


def test_nothing_but_aliases_stays_in_the_old_simulation_package():
    """Only the package's ``__init__`` and ARES-EA's alias stay in ``pigp_torch/simulation`` (git
    sees the ring's files as moved); a module the ring lacks is not found at the old path."""
    import pigp_torch.simulation as old

    names = {p.stem for p in Path(old.__file__).parent.glob("*.py")}
    assert names == {"__init__", "ares"}
    with pytest.raises(ModuleNotFoundError):
        importlib.import_module("pigp_torch.simulation.no_such_module")


def test_the_kinds_data_files_load_from_their_folders():
    """The SPEAR3 decks and the ARES-EA lattice and trials are package data of their kinds."""
    from pigp_torch.machines.ares_ea.simulation import default_trials_path, load_lattice
    from pigp_torch.machines.ring.deck import DECKS, deck_path, load_table

    for optics in DECKS:
        path = deck_path(optics)
        assert path.parent.parts[-3:] == ("machines", "ring", "data") and path.is_file()
    assert len(load_table("user")["elements"]) > 100
    assert {"elements", "knobs", "observables"} <= set(load_lattice())
    trials = default_trials_path()
    assert trials.is_file() and trials.parent.name == "data"
    assert trials.parent.parent.name == "ares_ea"
    assert (trials.parent / "README.md").is_file() and (path.parent / "README.md").is_file()
