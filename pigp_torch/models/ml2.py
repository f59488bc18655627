r"""The data-informed comparison GP: diagonal ARD RBF, hyperparameters by marginal likelihood."""

from __future__ import annotations

import math

import torch
from botorch.fit import fit_gpytorch_mll
from botorch.models import SingleTaskGP
from botorch.models.transforms import Normalize, Standardize
from gpytorch.constraints import GreaterThan
from gpytorch.kernels import RBFKernel, ScaleKernel
from gpytorch.mlls import ExactMarginalLogLikelihood
from gpytorch.priors import LogNormalPrior
from torch import Tensor

from pigp_torch._utils import DTYPE, check_bounds
from pigp_torch.models._data import training_data

_OUTCOME_KEYS = ("means", "stdvs", "_stdvs_sq", "_is_trained")


def _build(
    X: Tensor,
    Y: Tensor,
    bounds: Tensor,
    noise: float | None,
    outcome_transform: Standardize | None = None,
) -> SingleTaskGP:
    """Unfitted ML-II model; ``outcome_transform`` (eval mode) fixes the standardization."""
    d = bounds.shape[1]
    ls_prior = LogNormalPrior(loc=math.sqrt(2) + 0.5 * math.log(d), scale=math.sqrt(3))
    base = RBFKernel(
        ard_num_dims=d,
        lengthscale_prior=ls_prior,
        lengthscale_constraint=GreaterThan(2.5e-2, transform=None, initial_value=ls_prior.mode),
    )
    train_Yvar = None if noise is None else torch.full_like(Y, noise**2)
    return SingleTaskGP(
        X,
        Y,
        train_Yvar=train_Yvar,
        covar_module=ScaleKernel(base),
        input_transform=Normalize(d, bounds=bounds),
        outcome_transform=outcome_transform if outcome_transform is not None else Standardize(m=1),
    ).to(X)


def _hyperparameters(state_dict: dict[str, Tensor], model: SingleTaskGP, *, outcome: bool):
    """The entries of ``state_dict`` that are hyperparameters of ``model`` (raw parameters and,
    if ``outcome``, the standardization constants)."""
    keys = {n for n, _ in model.named_parameters()}
    if outcome:
        keys |= {f"outcome_transform.{k}" for k in _OUTCOME_KEYS}
    missing = sorted(keys - set(state_dict))
    if missing:
        raise ValueError(f"state_dict lacks hyperparameters {missing}; pass an ml2_gp state_dict")
    return {k: state_dict[k] for k in keys}


def _frozen_standardize(state_dict: dict[str, Tensor]) -> Standardize:
    ot = Standardize(m=1)
    ot.load_state_dict({k: state_dict[f"outcome_transform.{k}"] for k in _OUTCOME_KEYS})
    return ot.to(DTYPE).eval()


def _fit(model: SingleTaskGP) -> SingleTaskGP:
    mll = ExactMarginalLogLikelihood(model.likelihood, model)
    fit_gpytorch_mll(mll)
    return model.eval()


def ml2_gp(
    X,
    Y,
    *,
    bounds,
    archive: tuple[Tensor, Tensor] | None = None,
    refit: bool = True,
    noise: float | None = None,
    state_dict: dict[str, Tensor] | None = None,
) -> SingleTaskGP:
    r"""Data-informed GP with a diagonal ARD RBF kernel and ML-II hyperparameters.

    .. math::
        k(\mathbf x, \mathbf x') = \sigma_f^2 \exp\!\left(-\tfrac12 \sum_i
        \frac{(u_i - u'_i)^2}{\ell_i^2}\right), \qquad
        \mathbf u = (\mathbf x - \mathbf l) / (\mathbf h - \mathbf l),

    a constant mean, and Gaussian noise, on standardized outcomes (``Normalize(d, bounds)`` input
    and ``Standardize(m=1)`` outcome transforms; lengthscales :math:`\ell_i` are therefore in
    units of the knob RANGE). The hyperparameters :math:`(\ell, \sigma_f^2, c, \sigma_n^2)`
    maximize the marginal likelihood plus BoTorch's default weak hyperpriors (LogNormal on
    :math:`\ell` scaled with :math:`\sqrt d`, and on the noise when it is learned), via
    :func:`botorch.fit.fit_gpytorch_mll`.

    Which data set what:

    - ``refit=True``: hyperparameters are fitted on ``archive`` ∪ (X, Y) (just (X, Y) without an
      archive), starting from ``state_dict`` if given (a warm start: fewer iterations).
    - ``refit=False``: hyperparameters are taken from ``state_dict`` if given (no fitting at all,
      the cheap per-step path), otherwise fitted on the ``archive`` alone; they are then frozen
      (``requires_grad=False``).

    In both cases the returned model is CONDITIONED ON (X, Y) ONLY: the archive (a few hundred
    noisy samples near the operating point, possibly from another time or machine state) informs
    the hyperparameters, not the posterior. The standardization constants (mean, std) are those
    of the data the hyperparameters were fitted on, so :math:`\sigma_f^2` and the noise keep their
    meaning in objective units when transferred to the current data.

    Args:
        X: ``n x d`` knob settings.
        Y: ``n`` or ``n x 1`` observations.
        bounds: ``2 x d`` knob limits (fix the input normalization).
        archive: optional ``(X_a, Y_a)`` with shapes ``m x d`` and ``m`` (or ``m x 1``).
        refit: fit hyperparameters on archive ∪ current data (see above).
        noise: known noise standard deviation (objective units); ``None`` learns it.
        state_dict: ``model.state_dict()`` of a previous :func:`ml2_gp` model (warm start if
            ``refit``, the hyperparameters themselves if not).

    Returns:
        A :class:`~botorch.models.SingleTaskGP` in eval mode, trained on (X, Y).

    Raises:
        ValueError: bad shapes or values, ``refit=False`` with neither archive nor state_dict,
            or a ``state_dict`` that lacks the hyperparameters.
    """
    b = check_bounds(bounds)
    d = b.shape[1]
    X, Y = training_data(X, Y, d)
    if noise is not None:
        noise = float(noise)
        if not (math.isfinite(noise) and noise > 0):
            raise ValueError(f"noise must be a positive finite standard deviation, got {noise}")
    if archive is not None:
        if not (isinstance(archive, (tuple, list)) and len(archive) == 2):
            raise ValueError("archive must be a pair (X_a, Y_a)")
        Xa, Ya = training_data(*archive, d, name="archive ")
    if not refit and archive is None and state_dict is None:
        raise ValueError(
            "refit=False needs an archive or a state_dict to take hyperparameters from"
        )

    if refit:
        fit_X, fit_Y = (X, Y) if archive is None else (torch.cat([Xa, X]), torch.cat([Ya, Y]))
        fit_model = _build(fit_X, fit_Y, b, noise)
        if state_dict is not None:  # warm start; standardization is recomputed from the data
            fit_model.load_state_dict(
                _hyperparameters(state_dict, fit_model, outcome=False), strict=False
            )
        _fit(fit_model)
        if archive is None:
            return fit_model
        hyper = fit_model.state_dict()
    elif state_dict is not None:
        hyper = state_dict
    else:
        hyper = _fit(_build(Xa, Ya, b, noise)).state_dict()

    model = _build(X, Y, b, noise)
    hyper = _hyperparameters(hyper, model, outcome=True)  # validates the keys
    model = _build(X, Y, b, noise, outcome_transform=_frozen_standardize(hyper))
    model.load_state_dict(hyper, strict=False)
    if not refit:
        for p in model.parameters():
            p.requires_grad_(False)
    return model.eval()
