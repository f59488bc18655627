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
    r"""What the optimization loop needs from a machine.

    Attributes:
        knob_names: ``d`` knob names (control-system names on a real machine).
        bounds: ``2 x d`` allowed knob range (row 0 lower, row 1 upper).
    """

    knob_names: list[str]
    bounds: torch.Tensor

    def set(self, x: torch.Tensor) -> None:
        """Apply knob setting ``x`` (``d``); raise ``ValueError`` if it is not allowed."""
        ...

    def read(self) -> float:
        """Measure the objective at the current setting."""
        ...

    def get(self) -> torch.Tensor:
        """The current knob setting (``d`` float64)."""
        ...


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
    and :meth:`read`. The current setting is tracked here.

    Args:
        bounds: ``2 x d`` knob bounds.
        knob_names: ``d`` names.
        max_step: per-knob maximum change per :meth:`set` (scalar fraction of the half-range or
            ``d`` absolute tensor), or ``None``.
        x_init: ``d`` initial setting (default zeros), validated against the bounds only.
    """

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
    setpoints = getattr(machine, "setpoints", None)
    if callable(setpoints):
        return torch.as_tensor(setpoints(), dtype=DTYPE).reshape(-1).clone()
    acked = getattr(machine, "last_acknowledged", None)
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
    steps = ramp_steps(current, target, getattr(machine, "max_step", None))
    for x in steps:
        machine.set(x)
    return len(steps)
