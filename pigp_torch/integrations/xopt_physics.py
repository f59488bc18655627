r"""``pigp-physics`` as an Xopt generator (and so in Badger): :class:`PhysicsGenerator`.

A thin front end on :class:`~pigp_torch.optimizers.physics_bo.PhysicsModelBO`, the one
implementation of the method: the generator keeps one ``PhysicsModelBO``, tells it every new row
of its data (``add_data``) in order and asks it for each candidate (``generate(1)``), so on the
same data it proposes what ``pigp optimize`` / the benchmark's ``pigp-physics`` propose (the same
trust box, seeds and warm starts).

Xopt conventions: the VOCS must have one ``MAXIMIZE`` objective (the physics form describes a
peak) and exactly the prior's knobs as continuous variables (any order; candidates are dicts by
name); rows with ``xopt_error`` true or a non-finite objective are skipped. The step limit is
``max_travel_distances``, as in Xopt's Bayesian generators: a fraction of each variable's range,
measured from the last evaluated point (``PhysicsModelBO(travel_limit=2 * fraction)``); the trust
box (``step_limit``, a fraction of the half-range around the told point with the highest
posterior mean) is the method's own.

Tracking: the generator tells its optimizer every new row, however long the routine, and
:meth:`PhysicsGenerator.recommend` / :meth:`PhysicsGenerator.tracked` expose the optimizer's
current estimate of the optimum and of its tracked unknowns (what ``pigp optimize``'s track mode
leaves the knobs at and logs).

Serialization: the prior is stored as plain data (:meth:`PhysicsPrior.to_dict
<pigp_torch.prior.PhysicsPrior.to_dict>`); importing this module registers the generator in
Xopt's registry under ``"pigp_physics"``, so ``Xopt.from_yaml`` (and Badger, which lists Xopt's
registry) re-creates it. On reload the data is replayed (:func:`pigp_torch.data.runlog.replay`: one
ask per row, checked against the row) so that the optimizer's state is the one of the run; when the
rows were not all proposed by the generator (an initial design) they are told without asking
(the fit then starts cold once).
"""

from __future__ import annotations

import math
from typing import Any, ClassVar

import pandas as pd
import torch
from pydantic import Field, PrivateAttr, field_validator, model_validator

try:
    from xopt.generator import Generator, StateOwner
    from xopt.generators import generators as _XOPT_REGISTRY
except ImportError as err:  # pragma: no cover - depends on the environment
    raise ImportError(
        "pigp_torch.integrations.xopt_physics needs Xopt; install the extra: "
        "pip install 'pigp-torch[xopt]'"
    ) from err

from pigp_torch._utils import DTYPE
from pigp_torch.data.runlog import ReplayError, replay
from pigp_torch.integrations.xopt_vocs import (
    XOPT_ERROR,
    continuous_bounds,
    prior_as_dict,
    single_objective,
)
from pigp_torch.optimizers.physics_bo import PhysicsModelBO
from pigp_torch.prior import PhysicsPrior

__all__ = ["PhysicsGenerator"]


class PhysicsGenerator(Generator, StateOwner):
    r"""Xopt generator of ``pigp-physics`` (see the module docstring).

    Attributes:
        prior: the physics prior (a :class:`~pigp_torch.prior.PhysicsPrior`, its dict or the
            path of its JSON file; stored as the dict).
        prior_file: path of the prior's JSON file (default ``None``); when set, the prior is
            read from it at every construction or reload (the field a form such as Badger's
            settings editor shows; ``prior`` is then ignored).
        beta: UCB trade-off (default 4, :math:`\mu + 2\sigma`).
        step_limit: trust-box half-width, a fraction of each knob's half-range (default 0.6;
            ``None``: the whole box).
        max_travel_distances: hard step limit from the last evaluated point, a fraction of each
            variable's range: one value or one per VOCS variable (default ``None``: none).
        n_starts: Sobol starts of the acquisition search (default 8).
        seed: base seed (default 0; the benchmark derives one per run).
        noise: reading noise :math:`\sigma_n` in objective units (default: the prior's).
        options: further :class:`PhysicsModelBO` options (``info_every``, ``travel_limit``,
            ``center_prior``, ``shape_prior``, model options such as ``residual_std``).

    Raises:
        ValueError / pydantic.ValidationError: a VOCS other than one MAXIMIZE objective over the
            prior's knobs, bad option values, no prior, ``generate(n)`` with ``n != 1``.
    """

    name: ClassVar[str] = "pigp_physics"
    supports_single_objective: bool = Field(True, frozen=True, exclude=True)

    prior: dict[str, Any] | None = Field(
        None, description="PhysicsPrior.to_dict() of the physics prior (or give prior_file)"
    )
    prior_file: str | None = Field(
        None, description="path of the prior's JSON file; when set, the prior is read from it"
    )
    beta: float = Field(4.0, ge=0, description="UCB trade-off (4: mu + 2 sigma)")
    step_limit: float | None = Field(0.6, gt=0, description="trust box, fraction of half-range")
    max_travel_distances: float | list[float] | None = Field(
        None, description="step limit from the last point, fraction of each variable's range"
    )
    n_starts: int = Field(8, ge=0, description="Sobol starts of the acquisition search")
    seed: int = Field(0, description="base seed of the acquisition search")
    noise: float | None = Field(None, gt=0, description="reading noise (default: the prior's)")
    # a plain default, not default_factory: Badger lists a generator's defaults from
    # ``Field.default`` (pydantic copies a mutable default for each instance)
    options: dict[str, Any] = Field({}, description="PhysicsModelBO options")

    _optimizer: PhysicsModelBO | None = PrivateAttr(None)
    _rows_seen: int = PrivateAttr(0)
    _replayed: bool | None = PrivateAttr(None)

    @model_validator(mode="before")
    @classmethod
    def _prior_from_file(cls, data: Any) -> Any:
        # a form (Badger's GUI) edits the path; the file, when named, gives the prior
        if isinstance(data, dict) and data.get("prior_file"):
            data = {**data, "prior": prior_as_dict(data["prior_file"])}
        return data

    @field_validator("prior", mode="before")
    @classmethod
    def _validate_prior(cls, value: Any) -> dict[str, Any]:
        if value is None or (isinstance(value, dict) and not value):
            raise ValueError("no prior: give prior (a PhysicsPrior or its dict) or prior_file")
        return prior_as_dict(value)

    def model_post_init(self, context: Any) -> None:
        super().model_post_init(context)
        if self.prior is None:
            raise ValueError("no prior: give prior (a PhysicsPrior or its dict) or prior_file")
        self._check_vocs()
        self.optimizer  # build now: bad options fail at construction  # noqa: B018

    # -- the one optimizer ---------------------------------------------------------------------
    @property
    def physics_prior(self) -> PhysicsPrior:
        """The prior as a :class:`~pigp_torch.prior.PhysicsPrior`."""
        return PhysicsPrior.from_dict(self.prior)

    @property
    def knob_names(self) -> list[str]:
        """The prior's knob order (the optimizer's coordinates)."""
        return list(self.prior["knob_names"])

    def _check_vocs(self) -> None:
        _, maximize = single_objective(self.vocs)
        if not maximize:
            raise ValueError("pigp-physics models a peak: the VOCS objective must be MAXIMIZE")
        if sorted(self.vocs.variable_names) != sorted(self.knob_names):
            raise ValueError(
                f"the VOCS variables {self.vocs.variable_names} must be exactly the prior's knobs "
                f"{self.knob_names}"
            )

    def _bounds(self) -> torch.Tensor:
        b = continuous_bounds(self.vocs)  # in vocs.variable_names order
        perm = [self.vocs.variable_names.index(n) for n in self.knob_names]
        return b[:, perm]

    def _travel_limit(self):
        t = self.max_travel_distances
        if t is None:
            return None
        if isinstance(t, (int, float)):
            return 2.0 * float(t)
        if len(t) != len(self.knob_names):
            raise ValueError(f"max_travel_distances: {len(t)} values for {len(self.knob_names)}")
        by_name = dict(zip(self.vocs.variable_names, t, strict=True))
        return [2.0 * float(by_name[n]) for n in self.knob_names]

    def _new_optimizer(self) -> PhysicsModelBO:
        prior = self.physics_prior
        noise = prior.noise if self.noise is None else float(self.noise)
        return PhysicsModelBO(
            self._bounds(),
            prior,
            beta=self.beta,
            step_limit=self.step_limit,
            n_starts=self.n_starts,
            seed=self.seed,
            noise=noise,
            travel_limit=self._travel_limit(),
            **dict(self.options),
        )

    @property
    def optimizer(self) -> PhysicsModelBO:
        """The :class:`PhysicsModelBO` behind the generator (built on first use)."""
        if self._optimizer is None:
            self._optimizer = self._new_optimizer()
        return self._optimizer

    def _rows(self, data: pd.DataFrame | None, start: int = 0) -> list[tuple[list[float], float]]:
        """``(x in the prior's order, y)`` of the valid rows of ``data`` from row ``start``."""
        if data is None or len(data) <= start:
            return []
        objective = self.vocs.objective_names[0]
        out = []
        for _, row in data.iloc[start:].iterrows():
            if XOPT_ERROR in row and bool(row[XOPT_ERROR] is True):
                continue
            try:
                x = [float(row[n]) for n in self.knob_names]
                y = float(row[objective])
            except (KeyError, TypeError, ValueError):
                continue
            if all(math.isfinite(v) for v in (*x, y)):
                out.append((x, y))
        return out

    def _sync(self) -> None:
        """Tell the optimizer the rows of ``data`` it has not seen yet, in order."""
        if self.data is None:
            return
        for x, y in self._rows(self.data, self._rows_seen):
            self.optimizer.tell(torch.tensor(x, dtype=DTYPE), y)
        self._rows_seen = len(self.data)

    # -- Xopt's interface ----------------------------------------------------------------------
    def add_data(self, new_data: pd.DataFrame) -> None:
        """Append evaluated rows (Xopt's interface); they are told at the next ``generate``."""
        super().add_data(new_data)

    def set_data(self, data: pd.DataFrame) -> None:
        """Replace the data (Xopt calls this when it loads a dump) and rebuild the optimizer:
        replayed when every row after the first was proposed by it, else told row by row."""
        self.data = data
        rows = self._rows(data)
        self._optimizer = self._new_optimizer()
        records = [{"step": k, "x": x, "y": y} for k, (x, y) in enumerate(rows)]
        self._replayed = True
        try:
            replay(self._optimizer, records)
        except ReplayError:
            self._replayed = False
            self._optimizer = self._new_optimizer()
            for x, y in rows:
                self._optimizer.tell(torch.tensor(x, dtype=DTYPE), y)
        self._rows_seen = 0 if data is None else len(data)

    def generate(self, n_candidates: int) -> list[dict[str, float]]:
        """One candidate ``{variable: value}`` (``n_candidates`` must be 1: the method is
        sequential).

        Raises:
            ValueError: ``n_candidates != 1``, or no data yet (evaluate a start point first, e.g.
                the machine's current setting).
        """
        if int(n_candidates) != 1:
            raise ValueError(f"pigp_physics proposes one point at a time, asked {n_candidates}")
        self._sync()
        if not self.optimizer.n_told:
            raise ValueError("no data yet: evaluate a start point first (Xopt.evaluate_data)")
        x = self.optimizer.ask()
        by_name = dict(zip(self.knob_names, x.tolist(), strict=True))
        candidate = {n: by_name[n] for n in self.vocs.variable_names}
        candidate.update({k: v.value for k, v in self.vocs.constants.items()})
        return [candidate]

    def recommend(self) -> dict[str, float]:
        """The optimizer's current estimate of the best setting (its
        :meth:`~pigp_torch.optimizers.base.AskTellOptimizer.recommend`, after telling it every
        row of the data) as ``{variable: value}`` in the VOCS order, with the VOCS constants:
        where a long routine (a Badger run for a shift) leaves the knobs at its end.

        Raises:
            ValueError: no data yet.
        """
        self._sync()
        if not self.optimizer.n_told:
            raise ValueError("no data yet: evaluate a start point first (Xopt.evaluate_data)")
        x = torch.as_tensor(self.optimizer.recommend(), dtype=DTYPE).reshape(-1)
        by_name = dict(zip(self.knob_names, x.tolist(), strict=True))
        out = {n: by_name[n] for n in self.vocs.variable_names}
        out.update({k: v.value for k, v in self.vocs.constants.items()})
        return out

    def tracked(self) -> dict[str, tuple[float, str]]:
        """The optimizer's tracked unknowns now, ``{name: (value, unit)}`` (every row of the
        data told first; ``{}`` when it tracks none)."""
        self._sync()
        return dict(self.optimizer.tracked())

    @property
    def replayed(self) -> bool | None:
        """How the last :meth:`set_data` rebuilt the optimizer: ``True`` replayed (exact
        state), ``False`` told without asks, ``None`` no ``set_data`` yet."""
        return self._replayed

    @property
    def last_info(self) -> dict:
        """The optimizer's ``last_info`` after the last ``generate`` (trust box, fitted centre,
        fitted peak, timings)."""
        return dict(self.optimizer.last_info)


def register() -> None:
    """Put :class:`PhysicsGenerator` into Xopt's generator registry (done at import)."""
    _XOPT_REGISTRY[PhysicsGenerator.name] = PhysicsGenerator


register()
