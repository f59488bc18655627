r"""What a machine kind brings (:class:`MachineKind`) and the registry of kinds (:data:`KINDS`).

A *machine kind* is one accelerator family with everything the package needs to run on it:

* ``model(**options)``: its differentiable
  :class:`~pigp_torch.prior.machine_model.MachineModel` (knobs with bounds and units,
  observables, unknowns with their ranges, a batched differentiable ``observe``, a goal), from
  which the paper's prior, the ensemble of optima, the online fit of unknowns and the prior check
  are computed by the same code for every kind;
* ``simulator(**options)``: the simulation behind it (what a simulated machine reads);
* ``section()``: the pydantic class of its run-file section (``machine: {kind: <run_file_kind>,
  ...}``), ``check_run(config, method)`` (the checks of a run file that need the simulation),
  ``simulated_machine(config)`` (the machine ``pigp optimize`` runs on) and
  ``describe(config, machine)`` (that machine in words), ``methods_noise(section)`` and
  ``stated_noise(section)`` (the reading noise its methods and the loop are told);
* ``register_methods(register)``: the methods it adds to :data:`pigp_torch.methods.METHODS`
  (its :attr:`default_method` among them, or a generic one);
* ``benchmark(**options)``: its benchmark task (a table, one row per method, trial and step),
  ``register_bench(bench)`` its ``pigp bench <name>`` commands and ``register_commands(sub)`` its
  top-level ``pigp`` commands (the ring's ``compare``, ``demo``, ...);
* ``true_objective(config, say)``: the noise-free objective of its simulated machine, which the
  run report draws (:class:`TrueObjective`).

Each kind is a sub-package of :mod:`pigp_torch.machines` whose ``__init__`` defines ``KIND`` (a
:class:`MachineKind`) and imports nothing heavy: the registry finds every sub-package on first use
(:func:`pkgutil.iter_modules`, as entry points are found), so a new kind is one new folder. The
core (methods, loop) reads kinds only through :data:`KINDS`; a kind imports the core. As the
methods' registry and the run-file schema find the kinds while they are imported, a kind's
``__init__`` imports neither :mod:`pigp_torch.methods` nor :mod:`pigp_torch.loop` (its methods
import them when called).
"""

from __future__ import annotations

import importlib
import pkgutil
from collections.abc import Callable, Iterator, Mapping
from typing import TYPE_CHECKING, Any, NamedTuple

if TYPE_CHECKING:
    from torch import Tensor

    from pigp_torch.prior.machine_model import MachineModel


class TrueObjective(NamedTuple):
    r"""The noise-free objective of a run file's simulated machine
    (:meth:`MachineKind.true_objective`), for the run report's true curve.

    Attributes:
        values: ``n x d`` settings (the run's knob units) ``->`` ``n`` noise-free objective
            values (the run's objective unit).
        noise: the standard deviation of one reading (objective unit) the section states, or
            ``None`` (the report keeps the noise it was given).
        peak: the same objective, differentiable (autograd), when the report may search its
            maximum within the run's bounds; ``None``: no search.
    """

    values: Callable[[Tensor], Tensor]
    noise: float | None = None
    peak: Callable[[Tensor], Tensor] | None = None


class MachineKind:
    r"""A machine kind's plug-in (module docstring). Subclasses set the class attributes and
    override what the kind has; what it lacks raises :class:`NotImplementedError` naming it.

    Attributes:
        name: the registry key (``"spear3"``, ``"ares-ea"``).
        run_file_kind: ``machine.kind`` of its run-file section (``"sim"``, ``"ares-sim"``), or
            ``None`` when it has no simulated machine for ``pigp optimize``.
        default_method: the method its benchmark and run files use by default.
        title: one line saying what the machine is.
    """

    name: str = ""
    run_file_kind: str | None = None
    default_method: str = ""
    title: str = ""

    def model(self, **options: Any) -> MachineModel:
        """The kind's differentiable :class:`~pigp_torch.prior.machine_model.MachineModel`."""
        raise NotImplementedError(f"machine kind {self.name!r} has no model")

    def simulator(self, **options: Any) -> Any:
        """The kind's simulation (what its simulated machine reads)."""
        raise NotImplementedError(f"machine kind {self.name!r} has no simulator")

    def section(self) -> type:
        """The pydantic class of the kind's run-file section (``machine: {kind: ...}``)."""
        raise NotImplementedError(f"machine kind {self.name!r} has no run-file section")

    def check_run(self, config: Any, method: Any) -> None:
        """Check a validated run file (its :class:`~pigp_torch.methods.MethodSpec` ``method``)
        against the kind; every run file is shown to every kind. Default: a method built for
        this kind (``method.machine == name``) runs on its run-file section only.

        Raises:
            ValueError: the first problem (its message names the key).
        """
        if method.machine == self.name and config.machine.kind != self.run_file_kind:
            raise ValueError(
                f"method.name: {method.name} is a method of the {self.title}; it runs on "
                f"machine kind: {self.run_file_kind}"
            )

    def simulated_machine(self, config: Any) -> Any:
        """The simulated machine of a run file whose section is the kind's."""
        raise NotImplementedError(f"machine kind {self.name!r} has no simulated machine")

    def methods_noise(self, section: Any) -> float | None:
        """The reading noise (the objective's unit) the kind's simulated machine tells the
        method building the run's optimizer (:attr:`~pigp_torch.methods.RunContext.noise`;
        ``None``: the method keeps its own default). Default: the section's ``noise`` when
        above 0."""
        return section.noise if section.noise > 0 else None

    def stated_noise(self, section: Any) -> float | None:
        """The reading noise (the objective's unit) the run states to the loop for its
        re-read checks (:attr:`~pigp_torch.loop.RunOptions.noise`) when the run file gives no
        ``objective_noise``. Default ``None`` (then the prior's noise, if any)."""
        return None

    def describe(self, config: Any, machine: Any) -> str:
        """The simulated machine of a validated run file ``config`` whose section
        (``config.machine``) is the kind's, built as ``machine``, in words with the units of its
        numbers (the plan of ``pigp optimize --dry-run``: "plan: METHOD on the <this>").
        Default: the kind's title."""
        return f"simulated {self.title}"

    def true_objective(self, config: Any, say: Callable[[str], None]) -> TrueObjective | None:
        """The noise-free objective of the simulated machine of a run file whose section is the
        kind's (:class:`TrueObjective`; ``say`` takes one-line progress messages). Default
        ``None``: the report draws no true curve."""
        return None

    def register_bench(self, bench: Any) -> None:
        """Add the kind's ``pigp bench <name>`` to ``bench`` (the sub-parsers of ``pigp
        bench``: ``bench.add_parser(name, ...)``), importing nothing heavy. Default: none."""

    def register_commands(self, sub: Any) -> None:
        """Add the kind's top-level ``pigp`` commands to ``sub`` (the sub-parsers of ``pigp``:
        ``sub.add_parser(name, ...)``, each setting ``func``), importing nothing heavy. Default:
        none."""

    def register_methods(self, register: Callable[[Any], Any]) -> None:
        """Add the kind's methods with ``register(MethodSpec(...))``. Default: none."""

    def benchmark(self, **options: Any) -> Any:
        """Run the kind's benchmark task (a tidy table)."""
        raise NotImplementedError(f"machine kind {self.name!r} has no benchmark task")

    def drift_families(self) -> dict[str, frozenset[str]]:
        """The kind's drift and reality-gap families: name -> components (docs/drift_families.md).
        Default: none."""
        return {}

    def drift_machine(self, *, family: str, seed: int = 101, **options: Any) -> Any:
        """A simulated machine of drift family ``family`` with draw seed ``seed``, whose hidden
        state changes with its reading count and which keeps the true (noise-free) observables
        of its last reading in ``last_true_observables``."""
        raise NotImplementedError(f"machine kind {self.name!r} has no drift families")

    def __repr__(self) -> str:
        return f"<machine kind {self.name!r}: {self.title}>"


class KindRegistry(Mapping):
    r"""``name -> MachineKind`` of every sub-package of a package (default
    :mod:`pigp_torch.machines`), found and imported on first use, in name order.

    Raises:
        KeyError: (on lookup) a name that is no kind; the message lists the kinds.
        TypeError: (on discovery) a kind package without a ``KIND`` :class:`MachineKind`, or two
            kinds of one name.
    """

    def __init__(self, package: str = "pigp_torch.machines") -> None:
        self._package = package
        self._kinds: dict[str, MachineKind] | None = None

    def _load(self) -> dict[str, MachineKind]:
        if self._kinds is None:
            found: dict[str, MachineKind] = {}
            path = importlib.import_module(self._package).__path__
            for info in sorted(pkgutil.iter_modules(path), key=lambda i: i.name):
                if not info.ispkg:
                    continue
                module = importlib.import_module(f"{self._package}.{info.name}")
                kind = getattr(module, "KIND", None)
                if not isinstance(kind, MachineKind):
                    raise TypeError(f"{module.__name__} defines no KIND (a MachineKind)")
                if kind.name in found:
                    raise TypeError(f"two machine kinds are named {kind.name!r}")
                found[kind.name] = kind
            self._kinds = found
        return self._kinds

    def __getitem__(self, name: str) -> MachineKind:
        kinds = self._load()
        if name not in kinds:
            raise KeyError(f"no machine kind {name!r}; the kinds are {sorted(kinds)}")
        return kinds[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self._load())

    def __len__(self) -> int:
        return len(self._load())

    def by_run_file_kind(self, run_file_kind: str) -> MachineKind | None:
        """The kind whose run-file section is ``machine: {kind: run_file_kind}`` (``None``:
        none; ``sim`` and ``epics`` sections that no kind claims are the loop's own)."""
        return next((k for k in self.values() if k.run_file_kind == run_file_kind), None)


#: The machine kinds of the package: ``KINDS["spear3"]``, ``KINDS["ares-ea"]``.
KINDS = KindRegistry()
