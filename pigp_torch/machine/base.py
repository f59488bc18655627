r"""The machine interface: set knobs, read the objective, get the current knobs.

The same :func:`pigp_torch.loop.optimize` loop drives a simulated ring, an EPICS control system or
a benchmark through the :class:`Machine` protocol. Safety is enforced at the machine boundary:
:func:`check_setting` (used by :class:`GuardedMachine.set`) refuses settings outside the knob
bounds and, optionally, steps larger than a per-knob maximum.
"""

from __future__ import annotations

import math
from typing import Protocol, runtime_checkable

import torch

from pigp_torch._utils import DTYPE, as_knob_tensor, check_bounds, max_step_tensor


@runtime_checkable
class Machine(Protocol):
    r"""What the optimization loop reads from a machine: every member it uses, declared.

    :class:`GuardedMachine` implements the whole protocol: the five members a machine must
    provide (``knob_names``, ``bounds``, ``set``, ``read``, ``get``) and the defaults of the
    others, which a machine overrides where it has the thing (an EPICS machine its setpoint PVs,
    tolerance, objective limits and disconnection count; a simulated screen its observables).
    The loop reads these attributes directly; a machine without them is refused at the start.

    Attributes:
        knob_names: ``d`` knob names (control-system names on a real machine).
        bounds: ``2 x d`` allowed knob range (row 0 lower, row 1 upper; knob units).
        max_step: the machine's own per-knob step limit (anything
            :func:`~pigp_torch._utils.max_step_tensor` takes), or ``None`` (default: none).
        tolerance: ``d`` (or scalar) allowed :math:`|x_\mathrm{rb} - x|` of a readback in knob
            units, or ``None`` (default: the loop's ``readback_tol`` fraction of each range).
        objective_limits: ``(lower, upper)`` a valid reading lies in (objective units), or
            ``None`` (default: no limits).
        knob_units: ``d`` units of the knobs, or ``None`` (default: not stated).
        observable_names, observable_units: the ``m`` observables each reading also measures
            and their units, or ``None`` (default: the machine measures none).
        last_observables: ``m`` observables of the last reading, or ``None`` (default).
        last_reading: a dict describing the last reading (``"values"``: the single readings it
            averaged; timestamps), or ``None`` (default).
        last_acknowledged: ``d`` setpoints the machine last confirmed, or ``None``.
        disconnections: channel disconnections seen so far, or ``None`` (default: the machine
            has no channels).
    """

    knob_names: list[str]
    bounds: torch.Tensor
    max_step: object
    tolerance: object
    objective_limits: tuple[float, float] | None
    knob_units: tuple[str, ...] | None
    observable_names: tuple[str, ...] | None
    observable_units: tuple[str, ...] | None
    last_observables: torch.Tensor | None
    last_reading: dict | None
    last_acknowledged: torch.Tensor | None
    disconnections: int | None

    def set(self, x: torch.Tensor) -> None:
        """Apply knob setting ``x`` (``d``); raise ``ValueError`` if it is not allowed."""
        ...

    def read(self) -> float:
        """Measure the objective at the current setting."""
        ...

    def get(self) -> torch.Tensor:
        """The current knob setting (``d`` float64): the readbacks where the machine has them."""
        ...

    def setpoints(self) -> torch.Tensor | None:
        """The setpoints the machine holds (``d``, read from the control system), or ``None``
        where it does not tell setpoints from readbacks (default)."""
        ...

    def advance_noise(self, n_reads: int) -> None:
        """Move a simulated noise stream on as ``n_reads`` readings would (a resumed run); a
        no-op by default."""
        ...


#: Every member of :class:`Machine`; the first five a machine must provide itself,
#: :class:`GuardedMachine` gives the defaults of the others.
MACHINE_MEMBERS = (
    "knob_names", "bounds", "set", "read", "get", "max_step", "tolerance", "objective_limits",
    "knob_units", "observable_names", "observable_units", "last_observables", "last_reading",
    "last_acknowledged", "disconnections", "setpoints", "advance_noise",
)  # fmt: skip


def is_machine_objective(objective) -> bool:
    """``True`` for a :class:`Machine` (every member of :data:`MACHINE_MEMBERS`), ``False`` for
    a plain callable ``x -> float``.

    Raises:
        ValueError: an object with ``set``, ``read`` and ``get`` that lacks other members of the
            protocol (they are named), or neither a machine nor a callable.
    """
    lacking = [m for m in MACHINE_MEMBERS if not hasattr(objective, m)]
    if not lacking:
        return True
    if all(hasattr(objective, m) for m in ("set", "read", "get")):
        raise ValueError(
            f"the machine ({type(objective).__name__}) lacks the Machine protocol's {lacking}: "
            "derive it from GuardedMachine, which gives their defaults"
        )
    if not callable(objective):
        raise ValueError("objective must be a Machine or a callable x -> float")
    return False


def check_setting(
    x, bounds: torch.Tensor, *, current=None, max_step: torch.Tensor | None = None
) -> torch.Tensor:
    r"""Validate a knob setting against the bounds and a maximum step; return it as ``d`` float64.

    Args:
        x: ``d`` requested setting.
        bounds: ``2 x d`` knob bounds; a setting must satisfy :math:`\ell \le x \le h` exactly.
        current: ``d`` current setting (needed when ``max_step`` is given).
        max_step: ``d`` absolute per-knob limit on :math:`|x - x_\mathrm{current}|` (see
            :func:`max_step_tensor`), or ``None``.

    Raises:
        ValueError: wrong shape, NaN, a knob outside its bounds, or a step above ``max_step``.
    """
    d = bounds.shape[1]
    if not isinstance(x, torch.Tensor):  # lists/floats straight to float64, not via float32
        x = torch.as_tensor(x, dtype=DTYPE)
    X, _ = as_knob_tensor(x, d, name="setting")
    if X.shape[0] != 1:
        raise ValueError(f"setting must be a single point of shape ({d},), got {X.shape[0]} rows")
    x = X[0]
    out = ((x < bounds[0]) | (x > bounds[1])).nonzero().flatten().tolist()
    if out:
        raise ValueError(
            f"setting refused: knob indices {out} outside bounds "
            f"(values {x[out].tolist()}, lower {bounds[0, out].tolist()}, "
            f"upper {bounds[1, out].tolist()})"
        )
    if max_step is not None:
        if current is None:
            raise ValueError("max_step check needs the current setting")
        step = (x - torch.as_tensor(current, dtype=DTYPE)).abs()
        # tolerance for round-off of settings computed as current +- max_step
        too_big = (step > max_step * (1 + 1e-9)).nonzero().flatten().tolist()
        if too_big:
            raise ValueError(
                f"setting refused: step too large on knob indices {too_big} "
                f"(|change| {step[too_big].tolist()} > max_step {max_step[too_big].tolist()})"
            )
    return x


class GuardedMachine:
    r"""Base class for machines whose :meth:`set` is validated by :func:`check_setting`.

    Subclasses implement :meth:`_apply` (send a validated setting to the hardware / simulator)
    and :meth:`read`. The current setting is tracked here. Every other member of the
    :class:`Machine` protocol has its default here (no tolerance, objective limits, units,
    observables, reading description, disconnection count or setpoints of its own; ``advance_noise``
    does nothing); a subclass overrides those it has.

    Args:
        bounds: ``2 x d`` knob bounds.
        knob_names: ``d`` names.
        max_step: per-knob maximum change per :meth:`set` (scalar fraction of the half-range or
            ``d`` absolute tensor), or ``None``.
        x_init: ``d`` initial setting (default zeros), validated against the bounds only.
    """

    tolerance = None
    objective_limits: tuple[float, float] | None = None
    knob_units: tuple[str, ...] | None = None
    observable_names: tuple[str, ...] | None = None
    observable_units: tuple[str, ...] | None = None
    last_observables: torch.Tensor | None = None
    last_reading: dict | None = None
    disconnections: int | None = None

    def __init__(self, bounds, knob_names, *, max_step=None, x_init=None) -> None:
        self.bounds = check_bounds(bounds)
        d = self.bounds.shape[1]
        self.knob_names = [str(n) for n in knob_names]
        if len(self.knob_names) != d:
            raise ValueError(f"{len(self.knob_names)} knob names for {d} knobs")
        if len(set(self.knob_names)) != d:
            raise ValueError("knob names must be unique")
        self.max_step = max_step_tensor(max_step, self.bounds)
        x0 = torch.zeros(d, dtype=DTYPE) if x_init is None else x_init
        self._x = check_setting(x0, self.bounds).clone()

    @property
    def dim(self) -> int:
        return self.bounds.shape[1]

    def _apply(self, x: torch.Tensor) -> None:  # pragma: no cover - abstract
        raise NotImplementedError

    def set(self, x) -> None:
        """Validate ``x`` (``d``) against bounds and ``max_step``, apply it, and remember it."""
        x = check_setting(x, self.bounds, current=self._x, max_step=self.max_step)
        self._apply(x)
        self._x = x.clone()

    def get(self) -> torch.Tensor:
        """The current setting (``d`` float64, a copy)."""
        return self._x.clone()

    @property
    def last_acknowledged(self) -> torch.Tensor:
        """The last setting applied (``d`` float64, a copy): the setpoints the machine holds."""
        return self._x.clone()

    def read(self) -> float:  # pragma: no cover - abstract
        raise NotImplementedError

    def setpoints(self) -> torch.Tensor | None:
        """``None``: the machine does not tell setpoints from readbacks (see
        :attr:`last_acknowledged`)."""
        return None

    def advance_noise(self, n_reads: int) -> None:
        """Nothing to advance: the machine has no simulated noise stream."""


def ramp_steps(current: torch.Tensor, target: torch.Tensor, limit) -> list[torch.Tensor]:
    r"""The settings of a straight-line move from ``current`` to ``target`` within ``limit``.

    With per-knob limit :math:`m` (``d`` tensor, or ``None``: one step) the move
    :math:`\Delta = x_\mathrm{target} - x` is split into
    :math:`n = \lceil \max_i |\Delta_i| / m_i \rceil` equal steps; the last one is ``target``
    exactly. Intermediate points lie on the segment, hence inside the (convex) bounds.
    """
    delta = target - current
    n = 1
    if limit is not None:
        n = max(1, math.ceil(float((delta.abs() / limit).max()) - 1e-9))
    return [target if k == n else current + delta * (k / n) for k in range(1, n + 1)]


def setpoints_of(machine) -> torch.Tensor:
    """Where a ramp starts: the machine's setpoints (``setpoints()``, read from the IOC), else
    its last acknowledged setting (``last_acknowledged``), else ``get()`` — never a readback
    where the machine tells setpoints from readbacks."""
    setpoints = machine.setpoints()
    if setpoints is not None:
        return torch.as_tensor(setpoints, dtype=DTYPE).reshape(-1).clone()
    acked = machine.last_acknowledged
    if acked is not None:
        return torch.as_tensor(acked, dtype=DTYPE).reshape(-1).clone()
    return torch.as_tensor(machine.get(), dtype=DTYPE).reshape(-1).clone()


def ramp(machine: Machine, target) -> int:
    r"""Move ``machine`` to ``target`` in equal steps that respect its ``max_step`` (if any):
    the settings of :func:`ramp_steps` from :func:`setpoints_of` (never from readbacks), one
    ``set`` each.

    Returns:
        the number of ``set`` calls made.
    """
    target = torch.as_tensor(target, dtype=DTYPE).reshape(-1)
    current = setpoints_of(machine)
    steps = ramp_steps(current, target, machine.max_step)
    for x in steps:
        machine.set(x)
    return len(steps)
