r"""The shape of a peak, as the physics form sees it, from any objective with a background.

Near a peak of :math:`f` above its background :math:`f_\infty`, the function
:math:`g(\mathbf x) = (f(\mathbf x) - f_\infty)^{-2}` is a quadratic bowl

.. math:: g(\mathbf x) \approx c + (\mathbf x - \boldsymbol\mu)^\top B\,(\mathbf x - \boldsymbol\mu)

to second order, so :math:`B = \tfrac12 \nabla^2 g` at the peak (``d x d``, in (objective
unit)\ :sup:`-2` per knob unit squared) is the shape of the physics form
:math:`f = f_\infty + 1/\sqrt{c + (\mathbf x - \boldsymbol\mu)^\top B (\mathbf x -
\boldsymbol\mu)}` (:class:`~pigp_torch.models.InverseSqrtPeakModel`). The Hessian of
:math:`\log(f - f_\infty)` (:func:`~pigp_torch.prior.log_excess_hessian`, the paper's precision)
gives :math:`B` only at an exact stationary point; the Hessian of :math:`g` gives it wherever
:math:`g` is quadratic.

:func:`peak_shape_at` takes any differentiable ``f`` (``N x d -> N``): a ring's loss rate, or
the objective :math:`f = -\mathrm{goal}` of a :class:`~pigp_torch.prior.machine_model.MachineModel`
(:func:`~pigp_torch.prior.machine_model.machine_peak_shape`); :func:`mean_shape` averages the
shapes of an ensemble of machines (the prior's ``peak_shape``).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from pigp_torch._utils import DTYPE


def excess_derivatives(
    f: Callable[[Tensor], Tensor], f_inf: float, x: Tensor
) -> tuple[Tensor, Tensor]:
    r"""Hessian (``d x d``, symmetrized) and gradient (``d``) of
    :math:`g = (f - f_\infty)^{-2}` at ``x`` (``d``), by autograd.

    Args:
        f: ``N x d -> N``, differentiable (objective units).
        f_inf: the background :math:`f_\infty` (objective units).
        x: the point (knob units).
    """
    f_inf = float(f_inf)

    def g(z: Tensor) -> Tensor:
        return (f(z.unsqueeze(0)).reshape(()) - f_inf) ** -2

    x = torch.as_tensor(x, dtype=DTYPE).detach()
    H = torch.autograd.functional.hessian(g, x)
    G = torch.autograd.functional.jacobian(g, x)
    return (H + H.T) / 2, G


def peak_shape_at(f: Callable[[Tensor], Tensor], f_inf: float, x: Tensor) -> Tensor:
    r"""The peak's shape :math:`B = \tfrac12 \nabla^2 (f - f_\infty)^{-2}` at ``x`` (``d``):
    module docstring; ``d x d``."""
    H, _ = excess_derivatives(f, f_inf, x)
    return H / 2


def mean_shape(shapes: Tensor) -> Tensor:
    r""":math:`\bar B = \frac1n \sum_i B_i`: the mean of ``n x d x d`` peak shapes (symmetrized).

    The shape is a property of the optics that the errors perturb; the mean over machines is a
    better estimate for an unseen machine than any one machine's.

    Raises:
        ValueError: ``shapes`` is not ``n x d x d`` with ``n >= 1``.
    """
    shapes = torch.as_tensor(shapes, dtype=DTYPE)
    if shapes.ndim != 3 or shapes.shape[0] < 1 or shapes.shape[1] != shapes.shape[2]:
        raise ValueError(f"shapes must be n x d x d with n >= 1, got {tuple(shapes.shape)}")
    B = shapes.mean(0)
    return (B + B.T) / 2
