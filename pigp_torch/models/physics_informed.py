r"""The physics-informed GP: kernel, mean and noise all fixed by a :class:`PhysicsPrior`."""

from __future__ import annotations

import torch
from botorch import settings as botorch_settings
from botorch.models import SingleTaskGP
from gpytorch.kernels import ScaleKernel
from gpytorch.means import ConstantMean, Mean

from pigp_torch._utils import DTYPE
from pigp_torch.kernels import FullPrecisionRBFKernel, FullPrecisionRQKernel
from pigp_torch.models._data import training_data
from pigp_torch.models._prior_mean import prior_mean_value
from pigp_torch.prior import PhysicsPrior

#: Kernel families selectable by name.
KERNELS = {"rbf": FullPrecisionRBFKernel, "rq": FullPrecisionRQKernel}


def physics_informed_gp(
    X,
    Y,
    prior: PhysicsPrior,
    *,
    kernel: str = "rbf",
    mean: str | float | Mean = "f_inf",
    rq_alpha: float = 0.5,
) -> SingleTaskGP:
    r"""Build the physics-informed GP (PI-GP) conditioned on data; nothing is fitted.

    .. math::
        y = g(\mathbf x) + \varepsilon, \quad g \sim \mathcal{GP}\!\left(m,\;
        \sigma_f^2\, k_\Sigma(\mathbf x, \mathbf x')\right), \quad
        \varepsilon \sim \mathcal N(0, \sigma_n^2),

    with :math:`k_\Sigma` = :class:`~pigp_torch.kernels.FullPrecisionRBFKernel`
    (:math:`\exp(-\frac12 \delta^\top \Sigma \delta)`) or, with ``kernel="rq"``,
    :class:`~pigp_torch.kernels.FullPrecisionRQKernel` (:math:`(1 + q/2\alpha)^{-\alpha}`),
    :math:`\Sigma` = ``prior.precision``, :math:`\sigma_f^2` = ``prior.amplitude``,
    :math:`\sigma_n` = ``prior.noise`` and :math:`m` the constant prior mean. The posterior is
    the textbook one,
    :math:`\mu_* = m + K_{*}^\top (K + \sigma_n^2 I)^{-1} (\mathbf y - m)`.

    Every hyperparameter is frozen (``requires_grad=False``): the model is meant to be used as is,
    not passed to ``fit_gpytorch_mll``. Inputs are raw knob values in the prior's units (no input
    transform) and outputs raw objective values (no outcome transform). The model is returned in
    eval mode.

    Args:
        X: ``n x d`` knob settings (``d = prior.dim``).
        Y: ``n`` or ``n x 1`` observed objective values.
        prior: the physics prior.
        kernel: ``"rbf"`` (the paper's kernel) or ``"rq"`` (heavy-tailed variant).
        mean: ``"f_inf"`` (prior mean = ``prior.f_inf``, as in the paper), ``"zero"``, a float,
            or a gpytorch ``Mean`` module used as is (its parameters get frozen).
        rq_alpha: :math:`\alpha` of the RQ kernel (ignored for ``"rbf"``).

    Returns:
        A botorch :class:`~botorch.models.SingleTaskGP` in eval mode.

    Raises:
        ValueError: wrong shapes or non-finite data, unknown ``kernel`` or ``mean``.
    """
    if not isinstance(prior, PhysicsPrior):
        raise ValueError(f"prior must be a PhysicsPrior, got {type(prior).__name__}")
    X, Y = training_data(X, Y, prior.dim)
    if kernel not in KERNELS:
        raise ValueError(f"kernel must be one of {sorted(KERNELS)}, got {kernel!r}")
    if not isinstance(mean, Mean):
        mean = prior_mean_value(prior, mean, what="a float or a Mean")
    return frozen_gp(X, Y, prior.precision, prior.amplitude, prior.noise, mean, kernel=kernel,
                     rq_alpha=rq_alpha)  # fmt: skip


def frozen_gp(
    X: torch.Tensor,
    Y: torch.Tensor,
    precision: torch.Tensor,
    amplitude: float,
    noise: float,
    mean,
    *,
    kernel: str = "rbf",
    rq_alpha: float = 0.5,
    input_transform=None,
    outcome_transform=None,
) -> SingleTaskGP:
    r"""A frozen ``SingleTaskGP`` with kernel :math:`\sigma_f^2 k_P` (``kernel`` ``"rbf"`` or
    ``"rq"`` with precision ``precision`` in the model's input coordinates), fixed noise
    :math:`\sigma_n^2` and a constant prior ``mean`` (raw objective units) or a gpytorch ``Mean``
    used as is. With an ``outcome_transform`` (``Standardize``: shift :math:`m`, scale
    :math:`s`, fitted on ``Y`` at construction) the amplitude and mean are set in its units,
    :math:`\sigma_f^2 / s^2` and :math:`(\text{mean} - m)/s`, so the posterior in raw units is
    the same. ``X: n x d``, ``Y: n x 1`` float64 (validated by the caller); eval mode."""
    if kernel not in KERNELS:
        raise ValueError(f"kernel must be one of {sorted(KERNELS)}, got {kernel!r}")
    if kernel == "rq":
        base = FullPrecisionRQKernel(precision, alpha=rq_alpha)
    else:
        base = FullPrecisionRBFKernel(precision)
    covar_module = ScaleKernel(base).to(X)
    mean_module = mean if isinstance(mean, Mean) else ConstantMean().to(X)
    # raw knob units and raw objective values are intended: skip botorch's scaling warnings
    with botorch_settings.validate_input_scaling(False):
        model = SingleTaskGP(
            X,
            Y,
            train_Yvar=torch.full_like(Y, noise**2),  # Standardize divides it by s^2
            covar_module=covar_module,
            mean_module=mean_module,
            outcome_transform=outcome_transform,
            input_transform=input_transform,
        )
    if outcome_transform is not None:  # fitted now: amplitude and mean in its units
        shift = outcome_transform.means.reshape(()).to(DTYPE)
        scale = outcome_transform.stdvs.reshape(()).to(DTYPE)
    else:
        shift, scale = torch.zeros((), dtype=DTYPE), torch.ones((), dtype=DTYPE)
    # set from float64 tensors: gpytorch's setters would round Python floats through float32
    covar_module.outputscale = torch.tensor(amplitude, dtype=DTYPE) / scale**2
    if not isinstance(mean, Mean):
        mean_module.constant = (torch.tensor(mean, dtype=DTYPE) - shift) / scale
    for p in model.parameters():
        p.requires_grad_(False)
    return model.eval()
