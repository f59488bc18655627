r"""A simulated ARES-EA (DESY linac) behind the machine interface: five magnets, one screen.

The machine is one published trial (its incoming beam and misalignments, unknown to the
optimizer) tracked through :class:`~.simulation.AresSegment`. Each reading measures
the four beam numbers on the screen, :math:`o = (\mu_x, \sigma_x, \mu_y, \sigma_y)` in m, keeps
them in :attr:`AresMachine.last_observables` (the machine protocol is unchanged: ``read()``
returns the objective) and returns the chosen objective of them. With target :math:`t` and
:math:`s = +1` when the beam centre is on the screen (:math:`|\mu_x|, |\mu_y|` below the half
width and half height of the sensor), else :math:`-1`:

* ``"reward"`` (maximized; the published BO's objective without its additive constant):
  :math:`r = 10\,s - \ln \sum_i |o_i - t_i|` (the sum in m);
* ``"distance"`` (minimized; the published Nelder–Mead's beam distance with its 100× off-screen
  weight): :math:`d = \mathrm{MAE}(o, t) \cdot (100 \text{ if } s < 0 \text{ else } 1)`;
* ``"mae"`` (minimized): :math:`\mathrm{MAE}(o, t) = \tfrac14 \sum_i |o_i - t_i|` in m, the score;
* ``"neg-mae-um"`` (maximized): :math:`-10^6\,\mathrm{MAE}(o, t)`, minus the MAE in µm, for
  the methods whose physics prior describes a peak of a maximized objective (µm keep a GP's
  noise variance above GPyTorch's floor of 1e-6 for float64).

Screen noise (``noise``, m, default 0: noise-free as published): each of the four numbers gets
independent Gaussian noise :math:`\mathcal N(0, \sigma^2)` from the machine's own seeded generator;
a size reading is the absolute value of the noisy size (a fitted rms size is never negative).
"""

from __future__ import annotations

import torch

from pigp_torch._utils import DTYPE, as_knob_tensor
from pigp_torch.machine.base import GuardedMachine
from pigp_torch.machines.ares_ea.simulation import (
    KNOB_UNITS,
    OBSERVABLE_NAMES,
    START_SETTING,
    AresSegment,
    AresTrial,
    knob_bounds,
)

#: Objectives of the observables and whether each is maximized.
ARES_OBJECTIVES: dict[str, bool] = {
    "reward": True,
    "distance": False,
    "mae": False,
    "neg-mae-um": True,
}


def ares_objective(
    observables: torch.Tensor, target: torch.Tensor, on_screen: torch.Tensor, objective: str
) -> torch.Tensor:
    r"""The objective ``objective`` (:data:`ARES_OBJECTIVES`) of ``... x 4`` observables (m) for
    target ``4`` (m) and ``...`` on-screen flags; ``...`` tensor (module docstring)."""
    err = (observables - target).abs()
    if objective == "reward":
        sign = torch.where(on_screen, 1.0, -1.0).to(err)
        return 10.0 * sign - torch.log(err.sum(-1))
    mae = err.mean(-1)
    if objective == "distance":
        return mae * torch.where(on_screen, 1.0, 100.0).to(err)
    if objective == "mae":
        return mae
    if objective == "neg-mae-um":
        return -1e6 * mae
    raise ValueError(f"unknown ARES objective {objective!r}; known: {sorted(ARES_OBJECTIVES)}")


class AresMachine(GuardedMachine):
    r"""One ARES-EA trial as a :class:`~pigp_torch.machine.base.Machine`.

    Args:
        trial: the trial (incoming beam, misalignments, target).
        objective: ``"reward"`` (default, maximize), ``"distance"`` or ``"mae"`` (minimize),
            ``"neg-mae-um"`` (maximize).
        noise: screen noise standard deviation per beam number (m; default 0).
        seed: seed of the noise generator.
        unidirectional: restrict the quadrupoles to Q1 ≥ 0, Q2 ≤ 0, Q3 ≥ 0 (as the published BO).
        max_step: per-knob maximum change per ``set`` (see
            :class:`~pigp_torch.machine.base.GuardedMachine`), or ``None``.
        x_init: the initial setting (default the published start [10, −10, 0, 10, 0]).
        segment: an :class:`~.simulation.AresSegment` to share (default: new).
        bounds: ``2 x 5`` knob bounds inside the magnets' ranges (default: those ranges,
            :func:`~.simulation.knob_bounds` with ``unidirectional``).

    Attributes:
        knob_units: units of the knobs; observable_names: the four observables;
        observable_units: their units (m).
        maximize: whether ``read()`` is to be maximized.
        last_observables: ``4`` observables of the last reading (m), ``None`` before the first.
        n_reads: readings taken so far.
    """

    observable_names: tuple[str, ...] = OBSERVABLE_NAMES
    observable_units: tuple[str, ...] = ("m",) * len(OBSERVABLE_NAMES)
    knob_units: tuple[str, ...] = KNOB_UNITS

    def __init__(
        self,
        trial: AresTrial,
        *,
        objective: str = "reward",
        noise: float = 0.0,
        seed: int = 0,
        unidirectional: bool = False,
        max_step=None,
        x_init=None,
        segment: AresSegment | None = None,
        bounds=None,
    ) -> None:
        if objective not in ARES_OBJECTIVES:
            raise ValueError(
                f"unknown ARES objective {objective!r}; known: {sorted(ARES_OBJECTIVES)}"
            )
        noise = float(noise)
        if not (0.0 <= noise < float("inf")):
            raise ValueError(f"screen noise must be finite and >= 0 m, got {noise}")
        self.segment = AresSegment() if segment is None else segment
        x0 = torch.tensor(START_SETTING, dtype=DTYPE) if x_init is None else x_init
        limits = knob_bounds(unidirectional, self.segment.lattice)
        if bounds is not None:
            bounds = torch.as_tensor(bounds, dtype=DTYPE)
            if bounds.shape != limits.shape or bool(
                (bounds[0] < limits[0]).any() or (bounds[1] > limits[1]).any()
            ):
                raise ValueError(
                    f"knob bounds {bounds.tolist()} are not inside the magnets' ranges "
                    f"{limits.tolist()}"
                )
        super().__init__(
            limits if bounds is None else bounds,
            self.segment.knob_names,
            max_step=max_step,
            x_init=x0,
        )
        self.trial = trial
        self.target = trial.target.to(DTYPE)
        self.objective = objective
        self.maximize = ARES_OBJECTIVES[objective]
        self.noise = noise
        self.seed = int(seed)
        self._generator = torch.Generator().manual_seed(self.seed)
        self.last_observables: torch.Tensor | None = None
        self.n_reads = 0

    def _apply(self, x: torch.Tensor) -> None:
        """Nothing to send: the segment is tracked at read time."""

    def true_observables(self, x) -> torch.Tensor:
        r"""Noise-free ``N x 4`` observables (m) at ``N x d`` settings (``4`` for ``d``); does not
        change the knobs or the noise stream."""
        if not isinstance(x, torch.Tensor):
            x = torch.as_tensor(x, dtype=DTYPE)
        X, was_1d = as_knob_tensor(x, self.dim)
        with torch.no_grad():
            obs = self.segment.observe(X, self.trial.incoming, self.trial.misalignments)
        return obs[0] if was_1d else obs

    def objective_of(self, observables: torch.Tensor) -> torch.Tensor:
        """This machine's objective of ``... x 4`` observables (m)."""
        on = self.segment.on_screen(observables)
        return ares_objective(observables, self.target, on, self.objective)

    def mae(self, observables: torch.Tensor) -> torch.Tensor:
        """Mean absolute error (m) of ``... x 4`` observables to the target."""
        return (observables - self.target).abs().mean(-1)

    def read_observables(self) -> torch.Tensor:
        """One screen measurement at the current knobs: ``4`` observables (m), noisy if
        ``noise > 0``; also kept in :attr:`last_observables`."""
        obs = self.true_observables(self._x).clone()
        if self.noise > 0:
            obs = obs + self.noise * torch.randn(4, generator=self._generator, dtype=DTYPE)
            obs[1] = obs[1].abs()
            obs[3] = obs[3].abs()
        self.n_reads += 1
        self.last_observables = obs
        return obs.clone()

    def advance_noise(self, n_reads: int) -> None:
        """Move the noise stream on as ``n_reads`` readings would (a resumed run): with
        ``noise > 0`` that many :meth:`read_observables` at the current knobs; else nothing."""
        if self.noise > 0:
            for _ in range(int(n_reads)):
                self.read_observables()

    def read(self) -> float:
        """One measurement: the objective of :meth:`read_observables`."""
        return float(self.objective_of(self.read_observables()))

    def __call__(self, x) -> float:
        """Set the knobs to ``x`` (``d``) and take one reading."""
        self.set(x)
        return self.read()
