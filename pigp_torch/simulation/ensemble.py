r"""Where the optimum of a machine lies, over an ensemble of error seeds of the model ring.

A machine's coupling errors are random with known rms (DESIGN.md §2), so the knob setting that
decouples it is random too. Its distribution is a property of the lattice and the error model, not
of any one machine: the optics decide which resonance driving terms the errors excite and how the
knobs cancel them. Measured on 40 model rings (error seeds 144-183, 13 paper knobs): in the
coordinates whitened by the prior's Hessian, 90 % of the variance of the optimum lies in 3 of the
13 directions, and the optima of the 12 benchmark machines sit at a Mahalanobis distance² / 13 of
0.2-1.7 in the ensemble's covariance, i.e. they are typical members.

:func:`machine_centers` computes the optima; :func:`center_covariance` their second moment about
the nominal setting (zero knobs: the error model is symmetric, so the mean is zero up to sampling
noise). The result is the ``center_cov`` of a :class:`~pigp_torch.prior.PhysicsPrior`.
"""

from __future__ import annotations

import warnings

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


def machine_centers(
    seeds,
    *,
    knobs="paper13",
    optics: str = "achromat",
    reach: float = 4.0,
    progress: bool = False,
) -> tuple[list[int], torch.Tensor]:
    r"""Optimum of the loss rate of ``Spear3Coupling(s)`` for each seed, without the knob limit.

    The search (L-BFGS-B from zero knobs, ~2-3 s a ring at 13 knobs) runs in ``reach`` times the
    knob box, so an optimum just outside the box is found where it is, not on the boundary: it is
    the centre :math:`\boldsymbol\mu` of the physics form that
    :class:`~pigp_torch.models.InverseSqrtPeakModel` fits.

    Args:
        seeds: error seeds of the model rings.
        knobs, optics: as :class:`~pigp_torch.simulation.Spear3Coupling`.
        reach: search box = ``reach`` x the knob box (>= 1).
        progress: print one line per ring.

    Returns:
        ``(used_seeds, X)``: the seeds whose ring could be built and ``len(used_seeds) x d``
        optima. A seed whose error-scale calibration fails is skipped with a warning.

    Raises:
        ValueError: no seeds, ``reach < 1``, or no ring could be built.
    """
    seeds = [int(s) for s in seeds]
    if not seeds:
        raise ValueError("no seeds given")
    if not float(reach) >= 1.0:
        raise ValueError(f"reach must be >= 1, got {reach}")
    used, rows = [], []
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
        used.append(s)
        rows.append(x)
        if progress:
            print(f"  ensemble ring {k + 1}/{len(seeds)} (seed {s}): optimum {f:.3f} mA/min, "
                  f"max |knob| {float(x.abs().max()) / sim.knob_limit:.2f} of the limit",
                  flush=True)  # fmt: skip
    if not rows:
        raise ValueError(f"no ring of seeds {seeds} could be built")
    return used, torch.stack(rows)


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
