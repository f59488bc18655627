r"""Where the optimum of a machine lies, over an ensemble of error seeds of the model ring.

A machine's coupling errors are random with known rms (DESIGN.md §2), so the knob setting that
decouples it is random too. Its distribution is a property of the lattice and the error model, not
of any one machine: the optics decide which resonance driving terms the errors excite and how the
knobs cancel them. Measured on 40 model rings (error seeds 144-183, 13 paper knobs): in the
coordinates whitened by the prior's Hessian, 90 % of the variance of the optimum lies in 3 of the
13 directions, and the optima of the 12 benchmark machines sit at a Mahalanobis distance² / 13 of
0.2-1.7 in the ensemble's covariance, i.e. they are typical members.

:func:`ensemble_optima` computes the optima and the peak's shape at each; :func:`center_covariance`
the optima's second moment about the nominal setting (zero knobs: the error model is symmetric, so
the mean is zero up to sampling noise) and :func:`mean_shape` the mean shape. They are the
``center_cov`` and ``peak_shape`` of a :class:`~pigp_torch.prior.PhysicsPrior`.
"""

from __future__ import annotations

import warnings
from typing import NamedTuple

import torch

from pigp_torch._multistart import find_optimum
from pigp_torch._utils import DTYPE
from pigp_torch.simulation.spear3 import Spear3Coupling

#: First error seed of the default ensemble; far from the benchmark's machine seeds 1...N.
ENSEMBLE_SEED0 = 1001


def ensemble_seeds(size: int, first: int = ENSEMBLE_SEED0) -> list[int]:
    """The error seeds ``first ... first + size - 1`` of an ensemble of model rings."""
    if int(size) < 1:
        raise ValueError(f"an ensemble needs at least one ring, got size {size}")
    return list(range(int(first), int(first) + int(size)))


class EnsembleOptima(NamedTuple):
    """Optima of the model rings of an error ensemble (:func:`ensemble_optima`)."""

    #: error seeds of the rings that could be built
    seeds: list[int]
    #: ``n x d`` knob settings of the optima
    centers: torch.Tensor
    #: ``n x d x d`` peak shapes :math:`B_i` at the optima (:func:`peak_shape_at`)
    shapes: torch.Tensor

    def prior_fields(self) -> dict:
        """``center_cov`` and ``peak_shape`` of a :class:`~pigp_torch.prior.PhysicsPrior`
        (:func:`center_covariance`, :func:`mean_shape`)."""
        return {
            "center_cov": center_covariance(self.centers),
            "peak_shape": mean_shape(self.shapes),
        }

    @property
    def seed_range(self) -> list[int]:
        """``[first, last, count]`` of the seeds used (the provenance record)."""
        return [self.seeds[0], self.seeds[-1], len(self.seeds)]


def peak_shape_at(sim: Spear3Coupling, x: torch.Tensor) -> torch.Tensor:
    r"""Shape :math:`B = \tfrac12 \nabla^2 g` of :math:`g = (f - f_\infty)^{-2}` at ``x``.

    At a peak of the loss rate :math:`f` of ``sim``, :math:`g` is a quadratic bowl
    :math:`c + (\mathbf x - \boldsymbol\mu)^\top B (\mathbf x - \boldsymbol\mu)` to second order;
    this is the :math:`B` of :class:`~pigp_torch.models.InverseSqrtPeakModel` (knob units).
    """
    # Not prior.log_excess_hessian: that is log(f - f_inf), whose Hessian gives B only at an exact
    # stationary point (-H c there); g's Hessian is B wherever g is quadratic, and simulation/
    # does not import from prior/ (same layer, DESIGN.md §3).
    f_inf = float(sim.loss_background)

    def g(z: torch.Tensor) -> torch.Tensor:
        return (sim.loss_rate(z.unsqueeze(0)).reshape(()) - f_inf) ** -2

    H = torch.autograd.functional.hessian(g, torch.as_tensor(x, dtype=DTYPE).detach())
    return (H + H.T) / 4


def ensemble_optima(
    seeds,
    *,
    knobs="paper13",
    optics: str = "achromat",
    reach: float = 4.0,
    progress: bool = False,
) -> EnsembleOptima:
    r"""Optimum of the loss rate of ``Spear3Coupling(s)`` for each seed, without the knob limit,
    and the peak's shape there.

    The search (L-BFGS-B from zero knobs, ~2-6 s a ring at 13 knobs) runs in ``reach`` times the
    knob box, so an optimum just outside the box is found where it is, not on the boundary: it is
    the centre :math:`\boldsymbol\mu` of the physics form that
    :class:`~pigp_torch.models.InverseSqrtPeakModel` fits, and :func:`peak_shape_at` there its
    shape :math:`B` (one autograd Hessian, ~0.4 s).

    Args:
        seeds: error seeds of the model rings.
        knobs, optics: as :class:`~pigp_torch.simulation.Spear3Coupling`.
        reach: search box = ``reach`` x the knob box (>= 1).
        progress: print one line per ring.

    Returns:
        :class:`EnsembleOptima` of the rings that could be built. A seed is skipped with a
        warning when its error-scale calibration fails (the ring does not exist) or when the
        shape at its optimum is not positive definite (the search stopped off a peak).

    Raises:
        ValueError: no seeds, ``reach < 1``, or no ring could be used.
    """
    seeds = [int(s) for s in seeds]
    if not seeds:
        raise ValueError("no seeds given")
    if not float(reach) >= 1.0:
        raise ValueError(f"reach must be >= 1, got {reach}")
    used, rows, shapes = [], [], []
    for k, s in enumerate(seeds):
        try:
            sim = Spear3Coupling(s, knobs=knobs, optics=optics)
        except RuntimeError as err:  # calibration failure: this ring does not exist
            warnings.warn(f"ensemble seed {s} skipped: {err}", stacklevel=2)
            continue
        x, f = find_optimum(
            sim.loss_rate,
            sim.bounds * float(reach),
            n_starts=0,
            x_init=torch.zeros(1, sim.dim, dtype=DTYPE),
        )
        B = peak_shape_at(sim, x)
        if not torch.linalg.eigvalsh(B).min() > 0:
            warnings.warn(f"ensemble seed {s} skipped: the search stopped off a peak "
                          "(shape not positive definite)", stacklevel=2)  # fmt: skip
            continue
        used.append(s)
        rows.append(x)
        shapes.append(B)
        if progress:
            print(f"  ensemble ring {k + 1}/{len(seeds)} (seed {s}): optimum {f:.3f} mA/min, "
                  f"max |knob| {float(x.abs().max()) / sim.knob_limit:.2f} of the limit",
                  flush=True)  # fmt: skip
    if not rows:
        raise ValueError(f"no ring of seeds {seeds} could be used")
    return EnsembleOptima(used, torch.stack(rows), torch.stack(shapes))


def mean_shape(shapes: torch.Tensor) -> torch.Tensor:
    r""":math:`\bar B = \frac1n \sum_i B_i`: the mean of ``n x d x d`` peak shapes (symmetrized).

    The shape is a property of the optics that the errors perturb by 5-30 % per direction; the
    mean over rings is a better estimate for an unseen machine than any one ring's. Measured on
    the 12-seed spear3-13 benchmark (``pigp-physics``, 100 evaluations, 40 rings): 7 machines
    reached 95 % of the gain, median steps-to-95 % 72, median gain after 40 evaluations 0.92;
    with the model ring's own shape 7, 85.5 and 0.88 (and 4 against 7 within 60 evaluations).
    """
    shapes = torch.as_tensor(shapes, dtype=DTYPE)
    if shapes.ndim != 3 or shapes.shape[0] < 1 or shapes.shape[1] != shapes.shape[2]:
        raise ValueError(f"shapes must be n x d x d with n >= 1, got {tuple(shapes.shape)}")
    B = shapes.mean(0)
    return (B + B.T) / 2


def center_covariance(X: torch.Tensor) -> torch.Tensor:
    r""":math:`\frac1n \sum_i \mathbf x_i \mathbf x_i^\top`: second moment of ``n x d`` optima
    about zero knobs (the mean of a symmetric error model).

    Raises:
        ValueError: the matrix is singular (fewer optima than knobs, or degenerate ones).
    """
    X = torch.as_tensor(X, dtype=DTYPE)
    if X.ndim != 2 or X.shape[0] < 1:
        raise ValueError(f"X must be n x d with n >= 1, got shape {tuple(X.shape)}")
    C = X.T @ X / X.shape[0]
    C = (C + C.T) / 2
    if torch.linalg.eigvalsh(C).min() <= 0:
        raise ValueError(
            f"{X.shape[0]} optima in {X.shape[1]} knobs give a singular covariance: use an "
            f"ensemble of more than {X.shape[1]} rings"
        )
    return C
