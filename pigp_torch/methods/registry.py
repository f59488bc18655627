r"""The one registry of optimization methods: name -> builder, budget class and options.

A method is a :class:`MethodSpec`: a name, a builder ``(ctx: RunContext, **options) ->
optimizer``, the budget class (``"gp"`` or ``"direct"``, looked up in the benchmark's
``budgets``) and the builder's keyword options. Specs are plain data, so a variant is one entry::

    register(MethodSpec("pigp-rq", build_pigp, "gp", {"kernel": "rq"}))
    cheap = METHODS["pigp"].with_options(num_restarts=2, raw_samples=32)

The run files of ``pigp optimize`` accept the methods with ``run_file=True``
(:func:`run_file_methods`); the options a run file may give are the builder's keyword arguments
and, when the builder forwards ``**options`` to an optimizer class (``forwards_to``), that
class's keyword arguments (:func:`method_options`). A new optimizer is one module with its
builder and one :func:`register` call in :mod:`pigp_torch.methods`.
"""

from __future__ import annotations

import dataclasses
import inspect
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import torch

#: Budget classes of the protocol (evaluations, start point included).
DEFAULT_BUDGETS = {"gp": 100, "direct": 300}


@dataclass(frozen=True)
class RunContext:
    r"""What a builder may use for one run.

    Attributes:
        machine: the machine of this run (the benchmark's noisy
            :class:`~pigp_torch.machine.SimulatedMachine`); ``None`` when the optimizer is built
            before the machine (``pigp optimize``), then ``knob_bounds`` gives the bounds.
        prior: the physics prior computed from the MODEL ring (never the machine); ``None`` for
            methods that need none.
        seed: the run's seed.
        noise: the measurement noise standard deviation (objective units, mA/min); ``None``:
            unknown (each optimizer's own default is kept).
        archive_size: number of archive readings for data-informed methods (``0``, default: no
            archive, as on a live machine).
        archive: ``(size, *, spread, seed) -> (X_a: size x d, Y_a: size)``, readings of the
            machine near its operating point (the benchmark gives
            :func:`~pigp_torch.bench.archive.machine_archive` of its simulated machine);
            ``None``: none.
        maximize: maximize (default) or minimize the objective.
        knob_bounds: ``2 x d`` bounds; ``None``: the machine's.
    """

    machine: Any = None
    prior: Any = None
    seed: int = 0
    noise: float | None = 0.04
    archive_size: int = 0
    archive: Callable[..., tuple] | None = None
    maximize: bool = True
    knob_bounds: torch.Tensor | None = None

    @property
    def bounds(self) -> torch.Tensor:
        return self.machine.bounds if self.knob_bounds is None else self.knob_bounds


@dataclass(frozen=True)
class MethodSpec:
    """One method: ``builder(ctx, **options)`` returns a fresh ask/tell optimizer.

    Attributes:
        name: the method's name (the ``method`` column of a benchmark table, ``method.name`` of
            a run file).
        builder: ``(RunContext, **options) -> AskTellOptimizer``.
        budget: budget class, a key of the benchmark's ``budgets`` (``"gp"``/``"direct"``).
        options: keyword options passed to ``builder``.
        uses_center_ensemble: the method reads the prior's ``center_cov`` (so the benchmark
            computes the error ensemble for it).
        needs_prior: the builder needs ``ctx.prior`` and a maximized objective (the physics
            prior describes a peak).
        run_file: ``pigp optimize`` run files may name this method.
        forwards_to: the classes that the builder's ``**options`` go to (an optimizer, and the
            model it passes its own ``**options`` to); their keyword arguments are options too.
        fixed: keyword arguments of ``forwards_to`` that the builder sets itself (not options).
        offline_options: builder options that need a benchmark context (an archive of machine
            readings); run files may not give them.
        machine: the task the method is built for (``None``: any machine with bounds; e.g.
            ``"ares-ea"``: it reads that machine's target or fixed start).
    """

    name: str
    builder: Callable[..., Any]
    budget: str
    options: Mapping[str, Any] = field(default_factory=dict)
    uses_center_ensemble: bool = False
    needs_prior: bool = False
    run_file: bool = False
    forwards_to: tuple[type, ...] = ()
    fixed: tuple[str, ...] = ()
    offline_options: tuple[str, ...] = ()
    machine: str | None = None

    def build(self, ctx: RunContext):
        """A fresh optimizer for the run described by ``ctx``."""
        return self.builder(ctx, **dict(self.options))

    def with_options(self, name: str | None = None, **options) -> MethodSpec:
        """A copy with ``options`` overriding (and extending) this spec's options."""
        return dataclasses.replace(
            self, name=self.name if name is None else name, options={**self.options, **options}
        )

    def option_names(self) -> set[str]:
        """Option names a run file may give: the builder's keyword arguments and those of
        :attr:`forwards_to` (minus ``self``, ``bounds``, ``maximize``, :attr:`fixed` and
        :attr:`offline_options`)."""
        names = _keywords(self.builder) - {"ctx"}
        for cls in self.forwards_to:
            names |= _keywords(cls.__init__)
        return names - {"self", "bounds", "maximize", *self.fixed, *self.offline_options}


def _keywords(func) -> set[str]:
    params = inspect.signature(func).parameters.values()
    return {p.name for p in params if p.kind not in (p.VAR_KEYWORD, p.VAR_POSITIONAL)}


#: Every registered method by name (:func:`register` adds one).
METHODS: dict[str, MethodSpec] = {}


def register(spec: MethodSpec) -> MethodSpec:
    """Add ``spec`` to :data:`METHODS` (a name may be registered once)."""
    if spec.name in METHODS:
        raise ValueError(f"method {spec.name!r} is registered already")
    METHODS[spec.name] = spec
    return spec


def run_file_methods() -> tuple[str, ...]:
    """Names of the methods that ``pigp optimize`` run files accept, in registration order."""
    return tuple(name for name, spec in METHODS.items() if spec.run_file)


def method_options(name: str) -> set[str]:
    """Option names accepted by run-file method ``name``.

    Raises:
        ValueError: ``name`` is not a run-file method.
    """
    spec = METHODS.get(name)
    if spec is None or not spec.run_file:
        raise ValueError(f"unknown method {name!r}; known: {run_file_methods()}")
    return spec.option_names()


def resolve_methods(methods, registry: Mapping[str, MethodSpec] | None = None) -> list[MethodSpec]:
    """Names (looked up in ``registry``, default :data:`METHODS`) or :class:`MethodSpec`
    objects -> specs.

    Raises:
        ValueError: unknown name, duplicate method names, or an empty list.
    """
    registry = METHODS if registry is None else registry
    if isinstance(methods, (str, MethodSpec)):
        methods = [methods]
    specs = []
    for m in methods:
        if isinstance(m, MethodSpec):
            specs.append(m)
        elif m in registry:
            specs.append(registry[m])
        else:
            raise ValueError(f"unknown method {m!r}; known: {sorted(registry)}")
    names = [s.name for s in specs]
    if not specs:
        raise ValueError("no methods given")
    if len(set(names)) != len(names):
        raise ValueError(f"duplicate method names in {names}")
    return specs
