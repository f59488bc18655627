"""The loop reads declared protocols: the machine's (:class:`~pigp_torch.machine.base.Machine`)
and the optimizer's (:class:`~pigp_torch.optimizers.base.AskTellOptimizer`), never by probing."""

from __future__ import annotations

import ast
import importlib
import pkgutil
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

import pigp_torch
from pigp_torch.loop import optimize
from pigp_torch.machine.base import MACHINE_MEMBERS, GuardedMachine, Machine
from pigp_torch.optimizers.base import AskTellOptimizer
from pigp_torch.optimizers.nelder_mead import NelderMead
from tests.loop.problems import BOUNDS, D, bowl

LOOP = Path(pigp_torch.__file__).parent / "loop"
#: ``getattr(x, name, default)`` / ``hasattr`` calls in loop/ that ask no protocol question:
#: (file relative to loop/, the first argument's source).
ALLOWED = {
    ("signals.py", "signal"),  # SIGHUP exists on POSIX only: a platform question
    ("config/schema.py", "m"),  # a kind's run-file section may have no x_init: a schema question
}


def _probes(path: Path) -> list[tuple[str, str, int]]:
    """``(call, first argument, line)`` of every 3-argument ``getattr`` and every ``hasattr``."""
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name):
            name = node.func.id
            if (name == "getattr" and len(node.args) == 3) or name == "hasattr":
                out.append((name, ast.unparse(node.args[0]), node.lineno))
    return out


def test_the_loop_does_not_probe_machines_or_optimizers():
    """No ``getattr(x, name, default)`` or ``hasattr`` in the loop's modules: what it reads is
    declared by the machine and optimizer protocols (the allow-list asks no protocol question)."""
    found = [
        f"{p.relative_to(LOOP)}:{line}: {call}({arg}, ...)"
        for p in sorted(LOOP.rglob("*.py"))
        for call, arg, line in _probes(p)
        if (str(p.relative_to(LOOP)), arg) not in ALLOWED
    ]
    assert found == []


def test_the_probe_finder_sees_a_probe(tmp_path):
    """The AST scan above finds a 3-argument getattr and a hasattr (it can fail)."""
    f = tmp_path / "m.py"
    f.write_text("a = getattr(m, 'x', None)\nb = getattr(m, 'y')\nc = hasattr(m, 'z')\n")
    assert _probes(f) == [("getattr", "m", 1), ("hasattr", "m", 3)]


def test_machine_members_are_the_protocols_members():
    """:data:`MACHINE_MEMBERS` lists exactly the attributes and methods ``Machine`` declares."""
    declared = set(Machine.__annotations__) | {
        k for k, v in vars(Machine).items() if callable(v) and not k.startswith("_")
    }
    assert set(MACHINE_MEMBERS) == declared and len(MACHINE_MEMBERS) == len(declared)


def _machine_classes() -> list[type]:
    """Every machine class of the package (subclasses of GuardedMachine, all modules imported)."""
    for mod in pkgutil.walk_packages(pigp_torch.__path__, "pigp_torch."):
        if ".badger_plugins" in mod.name or ".integrations" in mod.name:
            continue  # Badger's and Xopt's glue import optional packages; they define no machine
        importlib.import_module(mod.name)
    todo, seen = [GuardedMachine], []
    while todo:
        cls = todo.pop()
        seen.append(cls)
        todo.extend(cls.__subclasses__())
    return [c for c in seen if c.__module__.startswith("pigp_torch.")]


def test_every_machine_of_the_package_declares_the_protocol():
    """Each machine class (the ring's simulated machine, the model machine, ARES, EPICS CA,
    pvAccess, the drift machines) has every protocol member not set per instance by
    ``GuardedMachine.__init__`` (``knob_names``, ``bounds``, ``max_step``)."""
    classes = _machine_classes()
    names = {c.__name__ for c in classes}
    expected = {"SimulatedMachine", "ModelMachine", "AresMachine", "EpicsMachine", "PvaMachine"}
    assert expected <= names
    per_instance = {"knob_names", "bounds", "max_step"}
    for cls in classes:
        lacking = [m for m in MACHINE_MEMBERS if m not in per_instance and not hasattr(cls, m)]
        assert lacking == [], cls.__name__


class Plain(GuardedMachine):
    """Two knobs, a bowl, the protocol's defaults."""

    def __init__(self) -> None:
        super().__init__(BOUNDS, ["a", "b"])

    def _apply(self, x) -> None:
        pass

    def read(self) -> float:
        return bowl(self._x)


def test_the_defaults_of_a_guarded_machine():
    """A GuardedMachine is a Machine with no setpoints, tolerance, limits, units, observables,
    reading description or channels; ``advance_noise`` changes nothing."""
    m = Plain()
    assert isinstance(m, Machine)
    assert m.setpoints() is None and m.tolerance is None and m.objective_limits is None
    assert m.knob_units is None and m.observable_names is None and m.observable_units is None
    assert m.last_observables is None and m.last_reading is None and m.disconnections is None
    m.advance_noise(3)
    assert m.read() == bowl(torch.zeros(2, dtype=D))


def test_a_machine_without_the_protocol_is_refused_by_name():
    """An object with set/read/get but none of the rest is refused before anything moves, the
    missing members named."""
    sets = []
    duck = SimpleNamespace(knob_names=["a", "b"], bounds=BOUNDS, set=sets.append,
                           get=lambda: torch.zeros(2, dtype=D), read=lambda: 0.0)  # fmt: skip
    with pytest.raises(ValueError, match=r"lacks the Machine protocol's \['max_step', 'tolerance'"):
        optimize(duck, NelderMead(BOUNDS), None, 3, handle_signals=False)
    assert sets == []


def test_an_optimizer_without_the_protocol_is_refused():
    """An ask/tell object that is not an AskTellOptimizer is refused by name; one that is runs."""

    class Loose:
        def ask(self):
            return torch.zeros(2, dtype=D)

        def tell(self, x, y):
            pass

    with pytest.raises(ValueError, match=r"optimizer \(Loose\) must be an AskTellOptimizer"):
        optimize(Plain(), Loose(), None, 3, handle_signals=False)
    out = optimize(Plain(), NelderMead(BOUNDS), None, 3, handle_signals=False)
    assert len(out) == 3 and out["method"].iloc[0] == NelderMead.name


def test_an_optimizer_declares_whether_it_fits_observables():
    """``uses_observables`` defaults to ``False`` on every AskTellOptimizer."""
    assert AskTellOptimizer.uses_observables is False
    assert NelderMead(BOUNDS).uses_observables is False
