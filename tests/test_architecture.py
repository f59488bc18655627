"""The import graph of the package, computed from the source, follows the layers.

Every import of a ``pigp_torch`` module is counted, at module level and inside functions (a
lazy import is still a dependency). A *unit* is a top-level module or subpackage of
``pigp_torch``; a unit may import only units of a LOWER layer (so two units of one layer do not
import each other), no module imports the package root, every unit has a layer, and within a
unit the modules import each other without a cycle.

=====  =========================================================================================
layer  units
=====  =========================================================================================
12     ``cli`` (the ``pigp`` parser), the package root (a lazy facade)
11     ``commands`` (one module per ``pigp`` command; each kind's commands through the registry;
       the ring's old command paths, aliases), ``badger_plugins``
       (Badger's entry point), ``benchmark`` (the first path of ``bench``: aliases only)
10     every machine kind: ``machines.<kind>`` (one folder each: ``machines.ares_ea``,
       ``machines.ring``); a kind imports the core, never another kind
9      ``bench`` (the library of ``pigp bench``: the BO speed run; the old path of the ring's
       benchmark, aliases), ``reporting`` (run reports and the dashboard), ``machines.contract``
       (the contract tests every machine kind inherits)
8      ``loop`` (the run loop: the loop, run files (``config``), runs (``run``), progress),
       ``testing`` (an older path of the ring's simulated EPICS servers: aliases only)
7      ``simulated_epics`` (the old path of the ring's simulated EPICS servers: aliases only)
6      ``methods`` (the method registry), ``machine`` (the Machine protocol and machines)
5      ``integrations`` (Xopt and Badger glue)
4      ``optimizers`` (ask/tell)
3      ``models`` (GP builders, posteriors), ``data`` (datasets, sampling, run logs and locks,
       lattice decks), ``machines`` (the registry of machine kinds, what a kind brings, the
       building blocks of a run-file section)
2      ``kernels``, ``prior``, ``surrogate``, ``simulation``
0      ``_utils`` (dtype and knob tensors, scipy's L-BFGS-B driven directly, multi-start),
       ``_version``
=====  =========================================================================================

The core (every unit but the kinds, ``commands`` and ``cli``) finds the kinds only through the
registry (``pigp_torch.machines.KINDS``, which imports each kind's folder by name when first used),
never by an import; the only exceptions are :data:`ALIASES`, modules at the old paths of moved
names that only re-export them (``simulation``, ``simulated_epics`` and ``testing`` are nothing
else now: the ring's simulation, benchmark and EPICS servers are in ``machines.ring``). An import
of an alias counts as an import of what it re-exports.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "pigp_torch"
ROOT = "<root>"

LAYERS: dict[str, int] = {
    **dict.fromkeys(("cli", ROOT), 12),
    **dict.fromkeys(("commands", "badger_plugins", "benchmark"), 11),
    **dict.fromkeys(("bench", "reporting", "machines.contract"), 9),
    **dict.fromkeys(("loop", "testing"), 8),
    "simulated_epics": 7,
    **dict.fromkeys(("methods", "machine"), 6),
    "integrations": 5,
    "optimizers": 4,
    **dict.fromkeys(("models", "data", "machines"), 3),
    **dict.fromkeys(("kernels", "prior", "surrogate", "simulation"), 2),
    **dict.fromkeys(("_utils", "_version"), 0),
}
#: The layer of every machine kind (a folder under ``pigp_torch/machines``).
KIND_LAYER = 10
#: Modules at the old paths of names that moved into a kind's folder: pure re-exports (a
#: docstring and ``from <kind module> import ...``, ``__all__``), allowed to import the kind.
ALIASES = frozenset(
    {
        "pigp_torch.machine.ares",
        "pigp_torch.benchmark.ares",
        "pigp_torch.simulation.ares",
        "pigp_torch.commands.bench_ares",
        "pigp_torch.simulation",
        "pigp_torch.bench",
        "pigp_torch.benchmark",
        "pigp_torch.simulated_epics",
        "pigp_torch.testing",
    }
)
#: Old package paths whose modules import as the moved modules themselves
#: (:func:`pigp_torch._utils.aliases.alias_package`): ``old.<m>`` is ``new.<m>`` (followed through
#: when ``new`` is an old path too); a module that exists at ``old`` is its own.
ALIAS_PACKAGES = {
    "pigp_torch.simulation": "pigp_torch.machines.ring",
    "pigp_torch.benchmark": "pigp_torch.bench",
    "pigp_torch.bench": "pigp_torch.machines.ring.bench",
    "pigp_torch.simulated_epics": "pigp_torch.machines.ring.simulated_epics",
    "pigp_torch.testing": "pigp_torch.simulated_epics",
    "pigp_torch.commands": "pigp_torch.machines.ring.commands",
}


#: The module of :func:`~pigp_torch._utils.aliases.alias_package`.
HELPER = "pigp_torch._utils.aliases"


def _module_name(path: Path) -> str:
    parts = ("pigp_torch", *path.relative_to(PACKAGE).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _modules() -> dict[str, Path]:
    return {_module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


def _imports(path: Path, name: str, known: set[str]) -> set[str]:
    """``pigp_torch`` modules imported anywhere in the file (``from a import b`` counts as
    ``a.b`` when that is a module)."""
    is_package = path.name == "__init__.py"
    package = name if is_package else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                module = ".".join([*base, *([node.module] if node.module else [])])
            else:
                module = node.module or ""
            targets = [f"{module}.{a.name}" for a in node.names if f"{module}.{a.name}" in known]
            targets = targets or [module]
        else:
            continue
        found |= {t for t in targets if t == "pigp_torch" or t.startswith("pigp_torch.")}
    return found


def _unit(module: str) -> str:
    """``machines.<kind>`` for a module of a kind's folder, else the top-level unit."""
    parts = module.split(".")
    if module == "pigp_torch.machines.contract":
        return "machines.contract"
    if len(parts) > 2 and parts[1] == "machines" and (PACKAGE / "machines" / parts[2]).is_dir():
        return f"machines.{parts[2]}"
    return parts[1] if len(parts) > 1 else ROOT


def _layer(unit: str) -> int:
    return LAYERS[unit] if unit in LAYERS else KIND_LAYER


def _graph() -> dict[str, set[str]]:
    modules = _modules()
    known = set(modules)
    return {name: _imports(path, name, known) for name, path in modules.items()}


def _resolve(target: str, graph: dict[str, set[str]], seen: frozenset[str] = frozenset()):
    """The modules an import of ``target`` reaches: a module of an alias package is the moved
    module (:data:`ALIAS_PACKAGES`), an alias module (:data:`ALIASES`) what it imports, each
    followed through; any other module itself."""
    old = next((o for o in ALIAS_PACKAGES if target.startswith(o + ".")), None)
    if target not in graph and old is not None:  # a module of an alias package
        return _resolve(ALIAS_PACKAGES[old] + target[len(old) :], graph, seen)
    if target in ALIAS_PACKAGES and not graph[target] - {HELPER}:  # names copied at run time
        return _resolve(ALIAS_PACKAGES[target], graph, seen | {target})
    if target not in ALIASES or target in seen:
        return {target}
    return set().union(*(_resolve(t, graph, seen | {target}) for t in graph[target]))


def _resolved_graph() -> dict[str, set[str]]:
    """:func:`_graph` with every import of an alias replaced by what it reaches (:func:`_resolve`;
    an alias module keeps its own imports)."""
    graph = _graph()
    return {
        m: set().union(*(_resolve(t, graph) for t in targets)) if m not in ALIASES else targets
        for m, targets in graph.items()
    }


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_every_unit_has_a_layer():
    units = {_unit(m) for m in _modules() if _unit(m) not in _kinds()}
    assert units - set(LAYERS) == set(), "add the new unit to LAYERS (and the docstring)"
    assert set(LAYERS) - units == set(), "a unit in LAYERS no longer exists"


def test_units_import_only_lower_layers_and_never_the_root():
    bad = []
    for module, targets in _resolved_graph().items():
        for target in targets:
            a, b = _unit(module), _unit(target)
            if target == "pigp_torch" and module != "pigp_torch":
                bad.append(f"{module} imports the package root")
            elif module in ALIASES:
                continue
            elif a != b and _layer(b) >= _layer(a):
                bad.append(f"{module} (layer {_layer(a)}) imports {target} (layer {_layer(b)})")
    assert bad == []


def _kinds() -> set[str]:
    folders = (PACKAGE / "machines").iterdir()
    return {f"machines.{p.name}" for p in folders if (p / "__init__.py").is_file()}


def test_each_machine_kind_is_a_folder_and_the_core_never_imports_one():
    """A kind (a folder under ``pigp_torch/machines``) imports the core; no module of the core
    imports a kind (the registry finds the kinds by name), no kind imports another, and the
    registry lists exactly the folders."""
    from pigp_torch.machines import KINDS

    assert _kinds() == {"machines.ares_ea", "machines.ring"}
    assert {type(k).__module__ for k in KINDS.values()} == {f"pigp_torch.{k}" for k in _kinds()}
    bad = []
    for module, targets in _resolved_graph().items():
        a = _unit(module)
        for target in targets:
            b = _unit(target)
            if b in _kinds() and a != b and a not in ("commands", "cli") and module not in ALIASES:
                bad.append(f"{module} imports the kind module {target}")
    assert bad == []


def test_an_import_of_an_alias_counts_as_an_import_of_the_kind():
    """The old paths lead into the ring's folder, through an alias package, an alias of an alias
    package and an alias module (so the checks above see a module of the core that imports
    ``pigp_torch.testing.ioc`` as importing the kind); a module that exists at an old path is its
    own."""
    graph = _graph()
    ring = "pigp_torch.machines.ring"
    assert _resolve("pigp_torch.testing.ioc", graph) == {f"{ring}.simulated_epics.ioc"}
    assert _resolve("pigp_torch.benchmark.protocol", graph) == {f"{ring}.bench.protocol"}
    assert _resolve("pigp_torch.simulation.spec", graph) == {f"{ring}.spec"}
    assert _resolve("pigp_torch.bench.bo_speed", graph) == {"pigp_torch.bench.bo_speed"}
    assert _resolve("pigp_torch.bench", graph) == {f"{ring}.bench"}
    assert _resolve("pigp_torch.testing", graph) == {f"{ring}.simulated_epics"}
    assert not any(_unit(t) in _kinds() for t in _resolve("pigp_torch.loop.config", graph))


def test_alias_modules_only_re_export_a_kind():
    """An alias module is a docstring, ``from <one kind module> import (...)`` and ``__all__``
    naming exactly the imported names, nothing else (an alias package's ``__init__`` also calls
    ``alias_package``, imported from ``pigp_torch._utils.aliases``); or, for an alias package, a
    docstring and ``alias_package(__name__, "<its new path>", globals())`` alone (the names are
    copied at import, :data:`ALIAS_PACKAGES` states where they come from)."""
    modules = _modules()
    for name in sorted(ALIASES):
        body = ast.parse(modules[name].read_text(encoding="utf-8")).body
        doc, middle, rest = body[0], body[1:-1], body[-1]
        assert isinstance(doc, ast.Expr) and isinstance(doc.value, ast.Constant), name
        calls = [n for n in body[1:] if isinstance(n, ast.Expr)]
        assert all(n.value.func.id == "alias_package" for n in calls), name
        if name in ALIAS_PACKAGES and len(body) == 3:  # the short form of an alias package
            (call,) = calls
            args = [ast.unparse(a) for a in call.value.args]
            assert args == ["__name__", repr(ALIAS_PACKAGES[name]), "globals()"], name
            assert body[1].module == HELPER, name
            continue
        imports = [n for n in middle if n not in calls and getattr(n, "module", "") != HELPER]
        assert imports and all(isinstance(n, ast.ImportFrom) for n in imports), name
        assert all(_unit(n.module) in _kinds() for n in imports), name
        assert isinstance(rest, ast.Assign) and rest.targets[0].id == "__all__", name
        exported = {e.value for e in rest.value.elts}
        assert exported == {a.name for n in imports for a in n.names}, name


def test_no_import_cycle_between_modules():
    assert _cycles(_graph()) == []


@pytest.mark.parametrize(
    ("source", "expected"),
    [
        ("from pigp_torch.loop import optimize\n", {"pigp_torch.loop"}),
        ("def f():\n    import pigp_torch.models.ml2\n", {"pigp_torch.models.ml2"}),
        ("from . import registry\n", {"pigp_torch.methods.registry"}),
        ("from pigp_torch import _utils\n", {"pigp_torch._utils"}),
        ("from pigp_torch import optimize\n", {"pigp_torch"}),
    ],
)
def test_the_import_finder_sees_every_form(tmp_path, source, expected):
    """Module-level, function-level, relative and package-member imports are all found (a
    finder that missed one would let an upward import through)."""
    path = tmp_path / "gp.py"
    path.write_text(source)
    known = set(_modules())
    assert _imports(path, "pigp_torch.methods.gp", known) == expected


def test_the_cycle_finder_finds_a_cycle():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert _cycles(graph) == [["a", "b", "c"]]


#: The Bayesian-optimization core: its parts and recipes (modules under these prefixes).
BO_CORE = (
    "pigp_torch.optimizers.bo",
    "pigp_torch.optimizers.bayesopt",
    "pigp_torch.optimizers.fast_bo",
    "pigp_torch.optimizers.physics_bo",
    "pigp_torch.optimizers.base",
    "pigp_torch.models.posterior",
    "pigp_torch.models.inverse_sqrt",
    "pigp_torch.models._inverse_sqrt_numpy",
    "pigp_torch.models._inverse_sqrt_fit",
    "pigp_torch.models.incremental_gp",
    "pigp_torch.models.physics_posterior",
    "pigp_torch.models.botorch_posterior",
    "pigp_torch.methods",
)
#: The recipes built on the core's parts; the parts never import them.
BO_RECIPES = ("bayesopt", "fast_bo", "physics_bo")


def test_the_bo_core_parts_import_no_recipe():
    """Inside the optimizers unit the core (``optimizers.bo``) sits below the recipes, and the
    posteriors (``models``) know nothing of acquisitions, searches or regions."""
    bad = []
    for module, targets in _graph().items():
        if module.startswith("pigp_torch.optimizers.bo"):
            bad += [f"{module} -> {t}" for t in targets
                    if t.rsplit(".", 1)[-1] in BO_RECIPES]  # fmt: skip
    assert bad == []


#: Modules whose functions are held to :data:`MAX_FUNCTION_LINES`: the BO core, the run loop,
#: the prior, the surrogate, and the machine kinds (the ring's benchmark protocol and job runner
#: among them).
SHORT_FUNCTIONS = (
    *BO_CORE,
    "pigp_torch.machines",
    "pigp_torch.loop",
    "pigp_torch.prior",
    "pigp_torch.surrogate",
)
MAX_MODULE_LINES = 400
MAX_FUNCTION_LINES = 80


def _long_functions(module: str, text: str) -> list[str]:
    return [
        f"{module}.{node.name}: {node.end_lineno - node.lineno + 1} lines"
        for node in ast.walk(ast.parse(text))
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))
        and node.end_lineno - node.lineno + 1 > MAX_FUNCTION_LINES
    ]


def test_no_module_of_the_package_is_over_400_lines():
    long_modules = []
    for module, path in _modules().items():
        n = path.read_text(encoding="utf-8").count("\n")
        if n > MAX_MODULE_LINES:
            long_modules.append(f"{module}: {n} lines")
    assert long_modules == []


def test_bo_core_and_loop_functions_are_short():
    """No function of the BO core, the run loop, the prior, the surrogate or the benchmark
    protocol over 80 lines (docstring included)."""
    long_functions = []
    for module, path in _modules().items():
        if module.startswith(SHORT_FUNCTIONS):
            long_functions += _long_functions(module, path.read_text(encoding="utf-8"))
    assert long_functions == []


def test_the_length_checks_see_a_long_function():
    body = "\n".join(f"    x{i} = {i}" for i in range(MAX_FUNCTION_LINES))
    text = f"def f():\n{body}\n\n\ndef g():\n    return 1\n"
    assert _long_functions("m", text) == [f"m.f: {MAX_FUNCTION_LINES + 1} lines"]
    assert _long_functions("m", "def g():\n    return 1\n") == []
    held = {m for m in _modules() if m.startswith(SHORT_FUNCTIONS)}
    assert {"pigp_torch.loop.core", "pigp_torch.prior.build", "pigp_torch.surrogate.train"} <= held
    assert "pigp_torch.machines.ring.bench.protocol" in held


def test_a_kinds_modules_are_one_unit_above_the_core():
    """A module of a kind's folder belongs to that kind (layer 10, above the benchmark and the
    loop it uses); the registry's modules are a low unit that the methods and the loop use."""
    assert _unit("pigp_torch.machines.ares_ea.benchmark") == "machines.ares_ea"
    assert _unit("pigp_torch.machines.ring") == "machines.ring"
    assert _unit("pigp_torch.machines.kind") == _unit("pigp_torch.machines") == "machines"
    assert _layer("machines.ring") == KIND_LAYER > _layer("bench") > _layer("loop")
    assert _layer("methods") > _layer("machines") and _layer("commands") > KIND_LAYER


#: Modules outside ``loop/`` that drive optimizers or machines: they read the declared protocols
#: (:class:`~pigp_torch.optimizers.AskTellOptimizer`, :class:`~pigp_torch.machine.base.Machine`).
PROTOCOL_READERS = ("data/runlog/replay.py", "machines/drift.py", "commands/optimize_output.py")


def test_the_modules_that_drive_optimizers_outside_the_loop_do_not_probe():
    """No ``getattr(x, name, default)`` or ``hasattr`` in :data:`PROTOCOL_READERS` (the loop's
    own modules are held by ``tests/loop/test_protocols.py``)."""
    from tests.loop.test_protocols import _probes

    assert [(f, _probes(PACKAGE / f)) for f in PROTOCOL_READERS] == [
        (f, []) for f in PROTOCOL_READERS
    ]
