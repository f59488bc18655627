r"""The physics-informed GP in Xopt's coordinates: :func:`physics_vocs_gp` and
:class:`PhysicsModelConstructor`.

Needs the optional extra ``xopt``.

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
round-off; ``tests/integrations/test_xopt.py`` checks 1e-8 relative). Nothing is trained: Xopt's
``train_model`` flag does not apply to this constructor.

Security note: Xopt's pydantic models ``torch.load`` (unpickle) any string field that names an
existing ``*.pt`` file when they are validated; build generators from trusted configurations only.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Literal

import pandas as pd
import torch
from botorch.models import ModelListGP, SingleTaskGP
from botorch.models.transforms import Normalize, Standardize
from pydantic import ConfigDict, Field, field_validator

try:
    from xopt.generators.bayesian.base_model import ModelConstructor
    from xopt.generators.bayesian.models.standard import StandardModelConstructor
    from xopt.generators.bayesian.utils import get_training_data
except ImportError as err:  # pragma: no cover - depends on the environment
    raise ImportError(
        "pigp_torch.integrations.xopt_gp needs Xopt; install the extra: "
        "pip install 'pigp-torch[xopt]'"
    ) from err

from pigp_torch._utils import DTYPE, check_bounds
from pigp_torch.integrations.xopt_vocs import prior_as_dict
from pigp_torch.models._prior_mean import prior_mean_value
from pigp_torch.models.physics_informed import KERNELS, frozen_gp
from pigp_torch.prior import PhysicsPrior


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
    mean_value = prior_mean_value(prior, mean)
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
    return frozen_gp(X, Y, P, prior.amplitude, prior.noise, mean_value, kernel=kernel,
                     rq_alpha=rq_alpha, input_transform=input_transform,
                     outcome_transform=outcome_transform)  # fmt: skip


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
