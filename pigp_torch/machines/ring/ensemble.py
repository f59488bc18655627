r"""Where the optimum of a machine lies, over an ensemble of error seeds of the model ring.

A machine's coupling errors are random with known rms, so the knob setting that decouples it is
random too. Its distribution is a property of the lattice and the error model, not of any one
machine: the optics decide which resonance driving terms the errors excite and how the knobs
cancel them.

:func:`ensemble_optima` computes the optima and the peak's shape at each, for any
:class:`~pigp_torch.machines.ring.ring.RingCoupling` (its lattice, knobs and calibration
with other error seeds); :func:`center_covariance` the optima's second moment about the nominal
setting (zero knobs: the error model is symmetric, so the mean is zero up to sampling noise) and
:func:`mean_shape` the mean shape. They are the ``center_cov`` and ``peak_shape`` of a
:class:`~pigp_torch.prior.PhysicsPrior`.
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from typing import NamedTuple

import torch

from pigp_torch._utils import DTYPE
from pigp_torch._utils.multistart import find_optimum
from pigp_torch.machines.ring.ring import RingCoupling
from pigp_torch.machines.ring.spear3 import Spear3Coupling
from pigp_torch.prior.peak_shape import excess_derivatives, mean_shape
from pigp_torch.prior.peak_shape import peak_shape_at as generic_peak_shape_at

#: box growth factors of the optimum search (times the knob box), up to ``reach``
GROWTH = (1.0, 2.0, 4.0, 8.0)
#: an optimum counts as on the search box's face beyond this fraction of the box
FACE = 0.999
#: largest accepted Newton step of g = (f - f_inf)^-2 at an optimum, in units of the knob box
STATIONARY_TOL = 1e-3

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
    #: ``(seed, reason)`` of every ring that could not be used
    failed: tuple = ()

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


def peak_shape_at(sim: RingCoupling, x: torch.Tensor) -> torch.Tensor:
    r"""Shape :math:`B = \tfrac12 \nabla^2 g` of :math:`g = (f - f_\infty)^{-2}` at ``x``.

    At a peak of the loss rate :math:`f` of ``sim``, :math:`g` is a quadratic bowl
    :math:`c + (\mathbf x - \boldsymbol\mu)^\top B (\mathbf x - \boldsymbol\mu)` to second order;
    this is the :math:`B` of :class:`~pigp_torch.models.InverseSqrtPeakModel` (knob units):
    :func:`pigp_torch.prior.peak_shape.peak_shape_at` of the loss rate and its background, the
    code every machine model's shape goes through.
    """
    return generic_peak_shape_at(sim.loss_rate, float(sim.loss_background), x)


def _g_derivatives(sim: RingCoupling, x: torch.Tensor):
    """Hessian and gradient of g = (f - f_inf)^-2 at ``x`` (autograd)."""
    return excess_derivatives(sim.loss_rate, float(sim.loss_background), x)


def unconstrained_optimum(sim: RingCoupling, reach: float = 4.0):
    r"""The loss-rate maximum of ``sim`` without the knob limit, and its peak shape.

    The search grows its box step by step (:data:`GROWTH` × the knob box, up to ``reach``):
    L-BFGS-B from zero knobs in the knob box, then, while the optimum sits on the search box's
    face, again from that optimum in the next larger box. So the search stays in the stable
    region around the working point instead of starting where the beam may be unstable. It is
    checked to be a maximum: finite, above the knobs-off value, a positive-definite shape
    :math:`B` (:func:`peak_shape_at`) and a Newton step :math:`\lVert B^{-1}\nabla g\rVert/2`
    below :data:`STATIONARY_TOL` of the knob box.

    Returns:
        ``(x, f, B)``: ``d`` optimum (knob units), its loss rate, ``d x d`` shape.

    Raises:
        ValueError: the search did not end on a maximum (the message says why).
    """
    zero = torch.zeros(1, sim.dim, dtype=DTYPE)
    f0 = float(sim.loss_rate(zero)[0])
    if not torch.isfinite(torch.tensor(f0)):
        raise ValueError("no stable beam with the knobs at zero")
    steps = [g for g in GROWTH if g < float(reach)] + [float(reach)]
    x, f = zero[0], f0
    for g in steps:
        box = sim.bounds * g
        x, f = find_optimum(sim.loss_rate, box, n_starts=0, x_init=x.unsqueeze(0))
        if not bool((x.abs() >= FACE * box[1]).any()):
            break
    else:
        raise ValueError(f"the optimum lies beyond {reach:g} x the knob box (on its face)")
    if not f > f0:
        raise ValueError(f"the search did not rise above the knobs-off loss rate ({f:.4g} mA/min)")
    H, G = _g_derivatives(sim, x)
    B = H / 2
    evals = torch.linalg.eigvalsh(B)
    if not evals.min() > 0:
        raise ValueError(
            f"the shape at the optimum is not positive definite (min eig {evals.min():.3g})"
        )
    step = torch.linalg.solve(B, G) / 2
    rel = float((step.abs() / sim.bounds[1]).max())
    if rel > STATIONARY_TOL:
        raise ValueError(f"not stationary: the Newton step is {rel:.3g} of the knob box")
    return x, f, B


def ensemble_optima(
    seeds,
    *,
    model: RingCoupling | None = None,
    knobs="paper13",
    optics: str = "user",
    reach: float = 4.0,
    progress: bool = False,
) -> EnsembleOptima:
    r"""Unconstrained optimum of the loss rate and the peak's shape there, for each error seed.

    The optimum is the centre :math:`\boldsymbol\mu` of the physics form that
    :class:`~pigp_torch.models.InverseSqrtPeakModel` fits, and its shape :math:`B`; both come
    from :func:`unconstrained_optimum` (a growing search box, each result checked to be a
    maximum). :func:`ring_optima` computes them ring by ring
    (several processes may each take a part of the seeds) and :func:`gather_optima` assembles
    the result; this function is the two in one process.

    Args:
        seeds: error seeds of the model rings.
        model: the ring (any :class:`~pigp_torch.machines.ring.ring.RingCoupling`); ring
            ``s`` is ``model.with_seed(s)``. Default:
            ``Spear3Coupling(knobs=knobs, optics=optics)``.
        knobs, optics: of the default SPEAR3 model.
        reach: largest search box, in units of the knob box (>= 1).
        progress: print one line per ring.

    Returns:
        :class:`EnsembleOptima` of the rings that could be used; ``failed`` lists the others
        with the reason (error-scale calibration failed, no maximum found). A warning names them.

    Raises:
        ValueError: no seeds, ``reach < 1``, or no ring could be used (the reasons are listed).
    """
    seeds = [int(s) for s in seeds]
    if not seeds:
        raise ValueError("no seeds given")
    found = ring_optima(seeds, model=model, knobs=knobs, optics=optics, reach=reach,
                        progress=progress)  # fmt: skip
    return gather_optima(found)


def ring_optima(
    seeds,
    *,
    model: RingCoupling | None = None,
    knobs="paper13",
    optics: str = "user",
    reach: float = 4.0,
    progress: bool = False,
    first_index: int = 0,
    total: int | None = None,
) -> list[tuple]:
    r"""The optimum of each ring ``model.with_seed(s)`` (:func:`unconstrained_optimum`).

    Args:
        seeds: error seeds; model, knobs, optics, reach: as :func:`ensemble_optima`.
        progress: print one line per ring (its optimum, seconds since the first ring began),
            numbered ``first_index + k + 1`` of ``total``
            (default ``len(seeds)``): a part of a larger ensemble numbers its rings in it.

    Returns:
        one ``(seed, x, B, reason)`` per seed: the ``d`` optimum and ``d x d`` shape, or
        ``None, None`` and why the ring could not be used.

    Raises:
        ValueError: ``reach < 1``.
    """
    if not float(reach) >= 1.0:
        raise ValueError(f"reach must be >= 1, got {reach}")
    total = len(seeds) if total is None else int(total)
    out = []
    t0 = time.perf_counter()
    for k, s in enumerate(int(s) for s in seeds):
        label = f"  ensemble ring {first_index + k + 1}/{total} (seed {s})"
        try:
            if model is None:
                sim = Spear3Coupling(s, knobs=knobs, optics=optics)
            else:
                sim = model.with_seed(s)
            x, f, B = unconstrained_optimum(sim, reach)
        except (RuntimeError, ValueError) as err:
            out.append((s, None, None, str(err)))
            if progress:
                print(f"{label}: skipped: {err}", flush=True)
            continue
        out.append((s, x, B, None))
        if progress:
            print(f"{label}: optimum {f:.3f} mA/min, "
                  f"max |knob| {float((x.abs() / sim.bounds[1]).max()):.2f} of the limit "
                  f"({time.perf_counter() - t0:.0f} s)", flush=True)  # fmt: skip
    return out


def gather_optima(results) -> EnsembleOptima:
    """:class:`EnsembleOptima` of :func:`ring_optima`'s results (in their order); a warning
    names the rings that could not be used.

    Raises:
        ValueError: no ring could be used (the reasons are listed).
    """
    results = list(results)
    used = [(s, x, B) for s, x, B, why in results if why is None]
    failed = tuple((s, why) for s, _, _, why in results if why is not None)
    if failed:
        lines = "; ".join(f"seed {s}: {why}" for s, why in failed)
        warnings.warn(
            f"{len(failed)} of {len(results)} ensemble rings skipped: {lines}", stacklevel=2
        )
    if not used:
        seeds = [r[0] for r in results]
        raise ValueError(f"no ring of seeds {seeds} could be used: {list(failed)}")
    return EnsembleOptima(
        [s for s, _, _ in used],
        torch.stack([x for _, x, _ in used]),
        torch.stack([B for _, _, B in used]),
        failed,
    )


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


def check_ensemble_size(size: int, n_knobs: int, option: str = "--center-ensemble") -> None:
    """Refuse, before any ring is computed, an ensemble too small for the covariance of the
    optimum of ``n_knobs`` knobs (it needs more rings than knobs: at least ``n_knobs + 1``;
    0 means no ensemble).

    Raises:
        ValueError: ``size`` negative, or between 1 and ``n_knobs``.
    """
    size, n_knobs = int(size), int(n_knobs)
    if size < 0:
        raise ValueError(f"{option} must be >= 0, got {size}")
    if 0 < size <= n_knobs:
        raise ValueError(
            f"{option} {size} is too small for {n_knobs} knobs: the covariance of the optimum "
            f"needs more rings than knobs, at least {n_knobs + 1} (0: no ensemble)"
        )


def ensemble_plan(size: int, data_meta: dict, knob_names, machine_seed=None):
    r"""The model ring and the error seeds of an ensemble of ``size`` rings for a prior of
    ``knob_names`` (the checks of :func:`with_center_ensemble`, before any ring is computed).

    Returns:
        ``(model, seeds)``: the data's ring (its error seed) and :func:`ensemble_seeds`.

    Raises:
        ValueError: as :func:`with_center_ensemble`.
    """
    from pigp_torch.machines.ring.spec import RingSpec, as_ring_spec

    check_ensemble_size(size, len(knob_names))
    if data_meta.get("ring"):
        spec = RingSpec.from_dict(data_meta["ring"])
    else:  # data written without a ring record: the SPEAR3 ring with the prior's knobs
        spec = as_ring_spec(None, knobs=tuple(knob_names))
    seeds = ensemble_seeds(size)
    for what, seed in (("model ring", data_meta.get("error_seed")), ("machine", machine_seed)):
        if seed in seeds:
            raise ValueError(f"the {what} (error seed {seed}) is among the ensemble seeds "
                             f"{seeds[0]}-{seeds[-1]}")  # fmt: skip
    model = spec.build(data_meta.get("error_seed", seeds[0]))
    if list(model.knob_names) != list(knob_names):
        raise ValueError("the data's ring has other knobs than the prior")
    return model, seeds


def with_center_ensemble(
    prior, size: int, data_meta: dict, machine_seed=None, *, progress=False, optima=None
):
    r"""``prior`` with ``center_cov`` and ``peak_shape`` from the optima of ``size`` simulated
    rings (error seeds :func:`ensemble_seeds`) of the data's ring.

    Args:
        prior: a :class:`~pigp_torch.prior.PhysicsPrior` (a dataclass; a copy is returned with
            the two fields and ``provenance["center_ensemble_seeds"]``).
        size: number of ensemble rings.
        data_meta: the surrogate's data metadata: ``ring`` (a
            :class:`~pigp_torch.machines.ring.spec.RingSpec` record; without one, the SPEAR3 ring
            with the prior's knobs) and ``error_seed`` (the model ring's).
        machine_seed: error seed of the machine under test, if known.
        progress: print a line and show a progress bar.
        optima: the :class:`EnsembleOptima` of :func:`ensemble_plan`'s rings when already
            computed (e.g. on other processes); default ``None``: computed here.

    Raises:
        ValueError: ``size`` not above the number of knobs (:func:`check_ensemble_size`), the
            model ring or the machine is among the ensemble seeds, or the data's ring has other
            knobs than the prior.
    """
    model, seeds = ensemble_plan(size, data_meta, prior.knob_names, machine_seed)
    if optima is None:
        if progress:
            print(f"optima of {size} ensemble rings (error seeds {seeds[0]}-{seeds[-1]})",
                  flush=True)  # fmt: skip
        optima = ensemble_optima(seeds, model=model, progress=progress)
    provenance = {**prior.provenance, "center_ensemble_seeds": optima.seed_range}
    return dataclasses.replace(prior, **optima.prior_fields(), provenance=provenance)
