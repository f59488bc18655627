r"""Physics priors inside Xopt / Badger, and Xopt generators as ask/tell optimizers.

Needs the optional extra ``xopt`` (``pip install "pigp-torch[xopt]"``); nothing else in the package
imports this module.

**Why a constructor of our own.** Xopt 3's :class:`~xopt.generators.bayesian.models.standard.\
StandardModelConstructor` always wraps its GPs in :class:`~botorch.models.transforms.Normalize`
(knobs mapped to :math:`[0, 1]` over the VOCS bounds) and
:class:`~botorch.models.transforms.Standardize` (outcomes shifted and scaled by the data's mean
and standard deviation), and learns the noise. A precision matrix, an amplitude, a prior mean or a
noise level given to it in raw units therefore silently means something else (Xopt's own
``HessianRBF`` in addition uses :math:`H^{-1}` as its metric, so a stiff direction gets a LONG
correlation, and keeps a trainable length scale). :class:`PhysicsModelConstructor` builds the
physics-informed GP with Xopt's transforms kept (so Xopt's tooling sees the model it expects) and
every hyperparameter mapped through them exactly. With :math:`W = \mathrm{diag}(u - \ell)` the
widths of the VOCS bounds, :math:`\bar y` and :math:`s` the mean and standard deviation of the
training outcomes (Xopt's ``Standardize``; :math:`s = 1` for a single point), the GP in model
coordinates :math:`\tilde x = W^{-1}(x - \ell)`, :math:`\tilde y = (y - \bar y)/s` has

.. math::
    \tilde\Sigma = W \Sigma W, \qquad \tilde\sigma_f^2 = \sigma_f^2 / s^2, \qquad
    \tilde\sigma_n^2 = \sigma_n^2 / s^2, \qquad \tilde m = (f_\infty - \bar y) / s,

so that its posterior, mapped back by BoTorch, is identical to
:func:`~pigp_torch.models.physics_informed_gp` on the same data (same mean and variance to
round-off; ``tests/test_xopt.py`` checks 1e-8 relative). Nothing is trained: Xopt's
``train_model`` flag does not apply to this constructor.

**Data frames.** Xopt keeps one row per evaluation with the VOCS variables, constants and outputs
as columns, plus ``xopt_runtime`` and ``xopt_error``; :func:`to_xopt_dataframe` turns the table of
:func:`pigp_torch.optimize` into that form.

**Ask/tell.** :class:`XoptOptimizer` drives any single-objective Xopt generator (e.g.
:class:`~xopt.generators.bayesian.UpperConfidenceBoundGenerator`) through ``tell`` ->
``generator.add_data`` and ``ask`` -> ``generator.generate(1)``, so :func:`pigp_torch.optimize`
and the benchmark can run stock Xopt next to our own optimizers.

Security note: Xopt's pydantic models ``torch.load`` (unpickle) any string field that names an
existing ``*.pt`` file when they are validated; build generators from trusted configurations only.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, Literal

import pandas as pd
import torch
from botorch import settings as botorch_settings
from botorch.models import ModelListGP, SingleTaskGP
from botorch.models.transforms import Normalize, Standardize
from gpytorch.kernels import ScaleKernel
from gpytorch.means import ConstantMean
from pydantic import ConfigDict, Field, field_validator

try:
    from gest_api.vocs import (
        ContextualVariable,
        ContinuousVariable,
        MaximizeObjective,
        MinimizeObjective,
    )
    from xopt.generators.bayesian.base_model import ModelConstructor
    from xopt.generators.bayesian.models.standard import StandardModelConstructor
    from xopt.generators.bayesian.utils import get_training_data
    from xopt.vocs import VOCS
except ImportError as err:  # pragma: no cover - depends on the environment
    raise ImportError(
        "pigp_torch.integrations.xopt needs Xopt; install the extra: pip install 'pigp-torch[xopt]'"
    ) from err

from pigp_torch._utils import DTYPE, check_bounds
from pigp_torch.models.physics_informed import KERNELS
from pigp_torch.optimizers.base import AskTellOptimizer
from pigp_torch.prior import PhysicsPrior

__all__ = [
    "PhysicsModelConstructor",
    "XoptOptimizer",
    "physics_vocs_gp",
    "to_xopt_dataframe",
    "vocs_from_bounds",
    "vocs_from_prior",
]

#: Columns Xopt's evaluator adds to every row.
XOPT_RUNTIME, XOPT_ERROR = "xopt_runtime", "xopt_error"


# ----------------------------------------------------------------------------- VOCS
def vocs_from_bounds(
    knob_names,
    bounds,
    *,
    objective: str = "loss_rate",
    maximize: bool = True,
    constants: Mapping[str, Any] | None = None,
) -> VOCS:
    r"""The Xopt VOCS of a tuning problem: one continuous variable per knob, one objective.

    Args:
        knob_names: ``d`` unique knob names, in the order of the columns of ``bounds`` (this is
            the order of ``vocs.variable_names`` and of the tensors :class:`XoptOptimizer`
            returns).
        bounds: ``2 x d`` knob bounds (row 0 lower, row 1 upper).
        objective: name of the objective output (default ``"loss_rate"``).
        maximize: ``MAXIMIZE`` (default: the loss rate rises as the beam gets smaller) or
            ``MINIMIZE``.
        constants: optional VOCS constants (name -> value) passed along with the variables.

    Returns:
        ``VOCS(variables={name: [lower, upper]}, objectives={objective: "MAXIMIZE"})``.

    Raises:
        ValueError: bounds of the wrong shape or empty, duplicate knob names, an objective name
            that clashes with a knob name.
    """
    if isinstance(knob_names, str):
        raise ValueError("knob_names must be a list of names, not one string")
    names = [str(n) for n in knob_names]
    if len(set(names)) != len(names):
        raise ValueError(f"knob names must be unique, got {names}")
    b = check_bounds(bounds)
    if b.shape[1] != len(names):
        raise ValueError(f"bounds must have shape (2, {len(names)}), got {tuple(b.shape)}")
    objective = str(objective)
    if objective in names:
        raise ValueError(f"objective name {objective!r} is also a knob name")
    variables = {
        n: [float(lo), float(hi)]
        for n, lo, hi in zip(names, b[0].tolist(), b[1].tolist(), strict=True)
    }
    return VOCS(
        variables=variables,
        objectives={objective: "MAXIMIZE" if maximize else "MINIMIZE"},
        constants=dict(constants or {}),
    )


def vocs_from_prior(prior: PhysicsPrior, bounds=None, **kwargs) -> VOCS:
    r"""The VOCS of the prior's knobs (:func:`vocs_from_bounds`).

    Args:
        prior: the physics prior; its ``knob_names`` name the variables (in this order).
        bounds: ``2 x d`` knob bounds in the prior's knob order (default ``prior.bounds``), e.g.
            a machine's ``bounds``.
        **kwargs: ``objective``, ``maximize``, ``constants`` of :func:`vocs_from_bounds`.

    Raises:
        ValueError: ``prior`` not a PhysicsPrior, or as :func:`vocs_from_bounds`.
    """
    if not isinstance(prior, PhysicsPrior):
        raise ValueError(f"prior must be a PhysicsPrior, got {type(prior).__name__}")
    return vocs_from_bounds(prior.knob_names, prior.bounds if bounds is None else bounds, **kwargs)


def _single_objective(vocs: VOCS) -> tuple[str, bool]:
    """``(name, maximize)`` of the VOCS's only objective."""
    if vocs.n_objectives != 1:
        raise ValueError(f"need exactly one objective in the VOCS, got {vocs.objective_names}")
    name = vocs.objective_names[0]
    obj = vocs.objectives[name]
    if isinstance(obj, MaximizeObjective):
        return name, True
    if isinstance(obj, MinimizeObjective):
        return name, False
    raise ValueError(f"objective {name!r} must be MAXIMIZE or MINIMIZE, got {type(obj).__name__}")


def prior_as_dict(value: Any) -> dict[str, Any]:
    """A prior field of a generator as plain, validated data (a :class:`PhysicsPrior` or its
    dict form).

    Raises:
        ValueError: anything else, or a dict that is not a valid prior.
    """
    if isinstance(value, PhysicsPrior):
        return value.to_dict()
    if isinstance(value, dict):
        return PhysicsPrior.from_dict(value).to_dict()  # validates every field
    raise ValueError(f"prior must be a PhysicsPrior or its dict, got {type(value).__name__}")


def _continuous_bounds(vocs: VOCS) -> torch.Tensor:
    """``2 x d`` bounds of the VOCS variables (all must be plain continuous variables)."""
    bad = [
        n
        for n, v in vocs.variables.items()
        if not isinstance(v, ContinuousVariable) or isinstance(v, ContextualVariable)
    ]
    if bad:
        raise ValueError(f"only continuous (non-contextual) variables are supported; got {bad}")
    return check_bounds(torch.tensor([list(v.domain) for v in vocs.variables.values()]).T)


# ----------------------------------------------------------------------------- the GP
def physics_vocs_gp(
    X,
    Y,
    prior: PhysicsPrior,
    input_names: list[str],
    input_bounds: Mapping[str, Any] | None = None,
    *,
    kernel: str = "rbf",
    rq_alpha: float = 0.5,
    mean: str | float = "f_inf",
    transform_inputs: bool = True,
    standardize_outputs: bool = True,
) -> SingleTaskGP:
    r"""The physics-informed GP with Xopt's input and outcome transforms, mapped exactly.

    The returned model is a BoTorch :class:`~botorch.models.SingleTaskGP` whose
    ``input_transform`` is :class:`~botorch.models.transforms.Normalize` over ``input_bounds``
    (if ``transform_inputs``) and whose ``outcome_transform`` is
    :class:`~botorch.models.transforms.Standardize` (if ``standardize_outputs``) — what Xopt's
    ``StandardModelConstructor`` builds — while kernel, amplitude, mean and noise are set in the
    transformed coordinates as in the module docstring, so that the posterior in raw units equals
    :func:`~pigp_torch.models.physics_informed_gp`'s. All parameters are frozen; eval mode.

    Args:
        X: ``n x d`` knob settings, columns in the order of ``input_names``.
        Y: ``n`` or ``n x 1`` observations (raw objective units).
        prior: the physics prior (knob units, objective units).
        input_names: the model's input names; must be a permutation of ``prior.knob_names``
            (the precision is permuted to match).
        input_bounds: ``{name: [lower, upper]}`` for ``Normalize`` (Xopt passes the VOCS bounds);
            required when ``transform_inputs``.
        kernel: ``"rbf"`` (the paper's kernel) or ``"rq"``.
        rq_alpha: :math:`\alpha` of the RQ kernel.
        mean: ``"f_inf"`` (constant prior mean :math:`f_\infty`), ``"zero"`` or a float (raw
            objective units).
        transform_inputs: keep Xopt's ``Normalize`` (default) or work in raw knob units.
        standardize_outputs: keep Xopt's ``Standardize`` (default) or raw objective units.

    Returns:
        A frozen :class:`~botorch.models.SingleTaskGP` in eval mode.

    Raises:
        ValueError: input names that do not match the prior's knobs, missing or degenerate bounds,
            unknown kernel or mean, bad data shapes.
    """
    if not isinstance(prior, PhysicsPrior):
        raise ValueError(f"prior must be a PhysicsPrior, got {type(prior).__name__}")
    input_names = [str(n) for n in input_names]
    if sorted(input_names) != sorted(prior.knob_names):
        raise ValueError(
            f"model inputs {input_names} must be exactly the prior's knobs {prior.knob_names} "
            "(fixed features or extra variables are not supported by the physics prior)"
        )
    if kernel not in KERNELS:
        raise ValueError(f"kernel must be one of {sorted(KERNELS)}, got {kernel!r}")
    mean_value = _mean_value(mean, prior)
    X = torch.as_tensor(X, dtype=DTYPE)
    Y = torch.as_tensor(Y, dtype=DTYPE)
    d = prior.dim
    if X.dim() != 2 or X.shape[1] != d or X.shape[0] == 0:
        raise ValueError(f"X must have shape (n >= 1, {d}), got {tuple(X.shape)}")
    Y = Y.reshape(X.shape[0], 1) if Y.numel() == X.shape[0] else Y
    if Y.shape != (X.shape[0], 1):
        raise ValueError(f"Y must have shape ({X.shape[0]},) or ({X.shape[0]}, 1)")
    if not (torch.isfinite(X).all() and torch.isfinite(Y).all()):
        raise ValueError("X and Y must be finite")

    perm = torch.tensor([prior.knob_names.index(n) for n in input_names])
    P = prior.precision[perm][:, perm]
    input_transform = None
    if transform_inputs:
        if input_bounds is None:
            raise ValueError("input_bounds are required when transform_inputs is True")
        missing = [n for n in input_names if n not in input_bounds]
        if missing:
            raise ValueError(f"input_bounds lack {missing}")
        B = torch.tensor([[float(v) for v in input_bounds[n]] for n in input_names], dtype=DTYPE).T
        B = check_bounds(B, "input_bounds")
        width = B[1] - B[0]
        # x = l + W u  =>  (x - x')^T P (x - x') = (u - u')^T (W P W) (u - u')
        P = width[:, None] * P * width[None, :]
        input_transform = Normalize(d, bounds=B)
    outcome_transform = Standardize(m=1) if standardize_outputs else None

    base = KERNELS[kernel](P, alpha=rq_alpha) if kernel == "rq" else KERNELS[kernel](P)
    covar_module = ScaleKernel(base).to(X)
    mean_module = ConstantMean().to(X)
    with botorch_settings.validate_input_scaling(False):
        model = SingleTaskGP(
            X,
            Y,
            train_Yvar=torch.full_like(Y, prior.noise**2),  # Standardize divides it by s^2
            covar_module=covar_module,
            mean_module=mean_module,
            input_transform=input_transform,
            outcome_transform=outcome_transform,
        )
    # the transforms are fitted now: map amplitude and mean into the model's outcome units.
    if outcome_transform is not None:
        shift = outcome_transform.means.reshape(()).to(DTYPE)
        scale = outcome_transform.stdvs.reshape(()).to(DTYPE)
    else:
        shift, scale = torch.zeros((), dtype=DTYPE), torch.ones((), dtype=DTYPE)
    # set from float64 tensors: gpytorch's setters would round Python floats through float32
    covar_module.outputscale = torch.tensor(prior.amplitude, dtype=DTYPE) / scale**2
    mean_module.constant = (torch.tensor(mean_value, dtype=DTYPE) - shift) / scale
    for p in model.parameters():
        p.requires_grad_(False)
    return model.eval()


def _mean_value(mean, prior: PhysicsPrior) -> float:
    if isinstance(mean, str):
        if mean not in ("f_inf", "zero"):
            raise ValueError(f'mean must be "f_inf", "zero" or a float, got {mean!r}')
        return prior.f_inf if mean == "f_inf" else 0.0
    try:
        value = float(mean)
    except (TypeError, ValueError):
        raise ValueError(f'mean must be "f_inf", "zero" or a float, got {mean!r}') from None
    if not math.isfinite(value):
        raise ValueError(f"mean must be finite, got {value}")
    return value


class PhysicsModelConstructor(ModelConstructor):
    r"""Xopt model constructor: the physics-informed GP for the objective, stock GPs otherwise.

    Give it to any Xopt Bayesian generator as ``gp_constructor``::

        vocs = vocs_from_prior(prior)
        gen = UpperConfidenceBoundGenerator(
            vocs=vocs, beta=4.0, gp_constructor=PhysicsModelConstructor(prior=prior)
        )

    The outcome named ``objective`` (default: the first outcome Xopt asks for, which is the
    VOCS's first objective — Xopt lists objectives before constraints and observables) gets
    :func:`physics_vocs_gp`: full-precision kernel
    :math:`\sigma_f^2 \exp(-\frac12 \delta^\top \Sigma \delta)` (correct convention, frozen),
    constant prior mean :math:`f_\infty`, fixed noise :math:`\sigma_n`, with Xopt's
    ``Normalize``/``Standardize`` accounted for exactly (or switched off with
    ``transform_inputs=False`` / ``standardize_outputs=False`` — same posterior either way).
    Other outcomes (constraints, observables) are built by ``other_outcomes``, a stock
    :class:`~xopt.generators.bayesian.models.standard.StandardModelConstructor` (trained as Xopt
    would). Per-point variances in ``<objective>_var`` data columns are ignored for the objective:
    its noise is the prior's.

    The prior is stored as plain data (:meth:`PhysicsPrior.to_dict`), so the generator dumps to
    JSON/YAML; a dumped generator reloads with this constructor only when it is passed back as an
    object (Xopt resolves constructors from strings by its own registry).

    Attributes:
        prior: the prior as a dict (pass a :class:`~pigp_torch.prior.PhysicsPrior` or its dict).
        objective: outcome that gets the prior; ``None``: the first outcome (first objective).
        kernel: ``"rbf"`` or ``"rq"``; ``rq_alpha`` its tail parameter.
        mean: ``"f_inf"``, ``"zero"`` or a float (raw objective units).
        transform_inputs, standardize_outputs: keep Xopt's transforms (default True).
        other_outcomes: constructor for every other outcome.
    """

    model_config = ConfigDict(arbitrary_types_allowed=True, validate_assignment=True)

    name: str = Field("pigp", frozen=True)
    prior: dict[str, Any] = Field(description="PhysicsPrior.to_dict() of the physics prior")
    objective: str | None = Field(None, description="outcome modelled with the physics prior")
    kernel: Literal["rbf", "rq"] = Field("rbf", description="full-precision kernel family")
    rq_alpha: float = Field(0.5, gt=0, description="tail parameter of the RQ kernel")
    mean: Literal["f_inf", "zero"] | float = Field("f_inf", description="constant prior mean")
    transform_inputs: bool = Field(True, description="keep Xopt's Normalize input transform")
    standardize_outputs: bool = Field(True, description="keep Xopt's Standardize transform")
    other_outcomes: StandardModelConstructor = Field(
        default_factory=StandardModelConstructor,
        description="constructor of the GPs of outcomes other than the objective",
    )

    @field_validator("prior", mode="before")
    @classmethod
    def _validate_prior(cls, value: Any) -> dict[str, Any]:
        return prior_as_dict(value)

    @property
    def physics_prior(self) -> PhysicsPrior:
        """The prior as a :class:`~pigp_torch.prior.PhysicsPrior`."""
        return PhysicsPrior.from_dict(self.prior)

    def build_model(
        self,
        input_names: list[str],
        outcome_names: list[str],
        data: pd.DataFrame,
        input_bounds: dict[str, list] | None = None,
        dtype: torch.dtype = torch.double,
        device: torch.device | str = "cpu",
    ) -> ModelListGP:
        """One model per outcome (Xopt's interface); see the class docstring.

        Raises:
            ValueError: ``objective`` not among ``outcome_names``, no data for it, or inputs that
                are not the prior's knobs.
        """
        outcome_names = list(outcome_names)
        target = self.objective
        if target is None:
            if not outcome_names:
                raise ValueError("no outcomes to model")
            target = outcome_names[0]  # Xopt lists the VOCS objectives first
        if target not in outcome_names:
            raise ValueError(f"objective {target!r} is not among the outcomes {outcome_names}")
        X, Y, _ = get_training_data(list(input_names), target, data)
        if X.shape[0] == 0:
            raise ValueError(f"no data to build the model of {target!r}")
        gp = physics_vocs_gp(
            X,
            Y,
            self.physics_prior,
            list(input_names),
            input_bounds,
            kernel=self.kernel,
            rq_alpha=self.rq_alpha,
            mean=self.mean,
            transform_inputs=self.transform_inputs,
            standardize_outputs=self.standardize_outputs,
        )
        others = [n for n in outcome_names if n != target]
        other_models = {}
        if others:
            stock = self.other_outcomes.build_model(
                list(input_names), others, data, input_bounds, dtype, device
            )
            other_models = dict(zip(others, stock.models, strict=True))
        models = [gp if n == target else other_models[n] for n in outcome_names]
        return ModelListGP(*models).to(dtype=dtype, device=device)


# ----------------------------------------------------------------------------- data frames
def to_xopt_dataframe(
    table: pd.DataFrame,
    vocs: VOCS,
    *,
    objective_column: str = "y",
    outputs: Mapping[str, str] | None = None,
    runtime_column: str | None = "eval_time_s",
) -> pd.DataFrame:
    r"""A pigp run log (the table of :func:`pigp_torch.optimize`) as Xopt data.

    Columns, in order: the VOCS variables (``vocs.variable_names``), the VOCS constants (their
    values), the outputs named by the VOCS, ``xopt_runtime`` (seconds of the evaluation, from
    ``runtime_column``; NaN if ``None``) and ``xopt_error`` (False). Index ``0 .. n-1`` (int64),
    as Xopt keeps it. Pass the result to ``Xopt(..., data=df)``, ``Xopt.add_data(df)`` or
    ``generator.add_data(df)`` to continue a run in Xopt / Badger.

    Args:
        table: one row per evaluation with one column per knob (named as the VOCS variables) and
            the observed objective.
        vocs: the VOCS of the problem.
        objective_column: table column holding the objective (default ``"y"``); it becomes the
            VOCS's only objective. Ignored if ``outputs`` is given.
        outputs: ``{vocs output name: table column}`` for several outputs.
        runtime_column: table column copied into ``xopt_runtime``.

    Raises:
        ValueError: knob or output columns missing, several objectives without ``outputs``, an
            output not named by the VOCS, non-finite knob values.
    """
    if not isinstance(table, pd.DataFrame):
        raise ValueError(f"table must be a pandas DataFrame, got {type(table).__name__}")
    names = list(vocs.variable_names)
    missing = [n for n in names if n not in table.columns]
    if missing:
        raise ValueError(f"table lacks knob columns {missing} named by the VOCS")
    if outputs is None:
        if vocs.n_objectives != 1:
            raise ValueError(
                f"the VOCS has objectives {vocs.objective_names}: map them with outputs="
            )
        outputs = {vocs.objective_names[0]: objective_column}
    unknown = [k for k in outputs if k not in vocs.output_names]
    if unknown:
        raise ValueError(f"outputs {unknown} are not named by the VOCS {vocs.output_names}")
    absent = [c for c in outputs.values() if c not in table.columns]
    if absent:
        raise ValueError(f"table lacks output columns {absent}")

    n = len(table)
    out = pd.DataFrame(index=pd.RangeIndex(n).astype("int64"))
    for name in names:
        out[name] = table[name].to_numpy(dtype="float64")
    if not torch.isfinite(torch.as_tensor(out[names].to_numpy())).all():
        raise ValueError("table has non-finite knob values")
    for name, value in vocs.constants.items():
        out[name] = value.value
    for name, column in outputs.items():
        out[name] = table[column].to_numpy(dtype="float64")
    if runtime_column is not None and runtime_column in table.columns:
        out[XOPT_RUNTIME] = table[runtime_column].to_numpy(dtype="float64")
    else:
        out[XOPT_RUNTIME] = float("nan")
    out[XOPT_ERROR] = False
    return out


# ----------------------------------------------------------------------------- ask/tell
class XoptOptimizer(AskTellOptimizer):
    r"""Any single-objective Xopt generator behind the ask/tell protocol.

    ``tell(x, y)`` appends one row (variables, VOCS constants, objective) to the generator's data
    (``generator.add_data``); ``ask()`` calls ``generator.generate(1)`` and returns the candidate
    as a ``d`` tensor in the order of ``vocs.variable_names`` (= ``knob_names``). The direction
    comes from the VOCS (``MAXIMIZE`` / ``MINIMIZE``). The candidate is clamped into the VOCS
    bounds as a last guard against round-off (a machine refuses a setting outside its bounds).

    Determinism: each ask runs under a forked torch RNG seeded with ``seed + n_told`` (Xopt's
    acquisition optimizer draws its random restarts from the global torch RNG; the global state is
    left untouched). Xopt's ``LBFGSOptimizer`` stops at ``max_time`` seconds (default 5), which
    can make a run depend on the machine's load; set ``numerical_optimizer.max_time=None`` for
    reproducible runs.

    After each ask, ``last_info`` holds Xopt's timings (``training``,
    ``acquisition_optimization``, seconds) and ``n_train``.

    Args:
        generator: an Xopt generator with ``vocs``, ``add_data`` and ``generate`` (e.g.
            ``UpperConfidenceBoundGenerator(vocs=...)``); its variables must be continuous.
        seed: base seed of the per-ask RNG.

    Raises:
        ValueError: a VOCS with other than one MAXIMIZE/MINIMIZE objective, or non-continuous
            variables.
    """

    name = "xopt"

    def __init__(self, generator, *, seed: int = 0) -> None:
        for attr in ("vocs", "add_data", "generate"):
            if not hasattr(generator, attr):
                raise ValueError(f"generator has no attribute {attr!r}: not an Xopt generator")
        vocs = generator.vocs
        objective, maximize = _single_objective(vocs)
        super().__init__(_continuous_bounds(vocs), maximize=maximize)
        self.generator = generator
        self.vocs = vocs
        self.objective = objective
        self.knob_names = list(vocs.variable_names)
        self.seed = int(seed)
        self.name = f"xopt-{getattr(generator, 'name', 'generator')}"
        self.last_info: dict = {}

    def tell(self, x, y: float) -> None:
        """Record ``y`` at ``x`` here and in the generator's data."""
        super().tell(x, y)
        row = dict(zip(self.knob_names, self.X[-1].tolist(), strict=True))
        row.update({k: v.value for k, v in self.vocs.constants.items()})
        row[self.objective] = self.Y[-1]
        self.generator.add_data(pd.DataFrame([row]))

    def ask(self) -> torch.Tensor:
        """``generator.generate(1)`` as a ``d`` float64 tensor inside the bounds."""
        if not self.Y:
            raise RuntimeError("no measurements yet: tell() the start point first")
        with torch.random.fork_rng():
            torch.manual_seed(self.seed + self.n_told)
            candidates = self.generator.generate(1)
        if len(candidates) != 1:
            raise RuntimeError(f"generator returned {len(candidates)} candidates, expected 1")
        x = torch.tensor([float(candidates[0][n]) for n in self.knob_names], dtype=DTYPE)
        if not torch.isfinite(x).all():
            raise RuntimeError(f"generator proposed a non-finite setting {x.tolist()}")
        x = torch.minimum(torch.maximum(x, self.bounds[0]), self.bounds[1])
        timing = getattr(self.generator, "computation_time", None)
        info = {"n_train": self.n_told}
        if isinstance(timing, pd.DataFrame) and len(timing):
            info.update({k: float(v) for k, v in timing.iloc[-1].items()})
        self.last_info = info
        return x
