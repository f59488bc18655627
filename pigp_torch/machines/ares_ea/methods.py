r"""Methods of the ARES-EA task (DESY linac, five magnets, one screen).

* ``published-bo``: the published BO recipe (:class:`~.published.
  PublishedAresBO`): unidirectional quadrupoles, knobs scaled to [−3, 3], the start and 4 uniform
  samples in a ±0.3 box around it, then SingleTaskGP + EI + ``optimize_acqf`` in the ±0.3 box
  around the last sample; maximizes the machine's ``"reward"`` objective.
* ``published-nm``: the published Nelder–Mead recipe on the project's
  :class:`~pigp_torch.optimizers.NelderMead`: bidirectional quadrupoles, classical coefficients,
  initial simplex steps of a quarter of each knob's range (±0.5 on knobs scaled to [−1, 1]), from
  the same start; minimizes the machine's ``"distance"`` objective (MAE, 100× off the screen). The
  published run minimized the step-to-step change of that distance (a "differential" reward); here
  the distance itself is minimized, which makes the objective stationary.

:data:`ARES_METHOD_OBJECTIVE` says which machine objective (:data:`~.machine.
ARES_OBJECTIVES`) each method reads; a method not listed reads ``"reward"``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch

from pigp_torch._utils import DTYPE
from pigp_torch.machines.ares_ea.published import PublishedAresBO
from pigp_torch.machines.ares_ea.simulation import INCOMING_NAMES, START_SETTING, knob_bounds
from pigp_torch.optimizers import NelderMead

if TYPE_CHECKING:  # the registry imports this module while it registers the kind's methods
    from pigp_torch.methods.registry import RunContext

#: The machine objective each ARES method reads (``read()`` of
#: :class:`~.machine.AresMachine`).
ARES_METHOD_OBJECTIVE: dict[str, str] = {
    "published-bo": "reward",
    "published-nm": "distance",
    "ares-physics": "mae",
}


def ares_objective_for(method: str) -> str:
    """The machine objective method ``method`` reads (default ``"reward"``)."""
    return ARES_METHOD_OBJECTIVE.get(method, "reward")


def build_published_bo(ctx: RunContext, *, unidirectional: bool = True, **options):
    """The published BO recipe; ``unidirectional`` restricts the quadrupoles as published
    (Q1 ≥ 0, Q2 ≤ 0, Q3 ≥ 0) within the machine's bounds."""
    bounds = ctx.bounds
    if unidirectional:
        uni = knob_bounds(unidirectional=True)
        bounds = torch.stack([torch.maximum(bounds[0], uni[0]), torch.minimum(bounds[1], uni[1])])
    x0 = torch.tensor(START_SETTING, dtype=DTYPE)
    return PublishedAresBO(bounds, x0=x0, seed=ctx.seed, maximize=ctx.maximize, **options)


def build_published_nm(ctx: RunContext, *, initial_simplex_size: float = 0.25, **options):
    """The published Nelder–Mead recipe (classical coefficients, a quarter-range simplex)."""
    options.setdefault("adaptive", False)
    return NelderMead(
        ctx.bounds, initial_simplex_size=initial_simplex_size, maximize=ctx.maximize, **options
    )


#: The unknowns ``ares-physics`` fits: the incoming beam's transverse centroid and sizes (the
#: optics of the segment do not depend on the energy, bunch length or energy spread) and the
#: eight misalignments.
ARES_FITTED_INCOMING: tuple[str, ...] = INCOMING_NAMES[1:9]


#: The quadrupoles whose calibration (k1 acted / k1 set) ``ares-physics`` fits.
ARES_CALIBRATED_QUADS: tuple[str, ...] = ("AREAMQZM1", "AREAMQZM2", "AREAMQZM3")

#: Half width of the quadrupoles' calibration range (fraction of k1): the prior of each
#: quadrupole's gain is centred at 1 with this half width (a standard deviation of
#: ``half / sqrt(3)`` in the fit).
ARES_QUAD_GAIN_HALF_WIDTH = 0.05


def ares_model_parts(
    segment=None,
    lattice=None,
    quad_gain_half_width=ARES_QUAD_GAIN_HALF_WIDTH,
    screen_resolution=0.0,
):
    r"""The ARES-EA model for :class:`~pigp_torch.optimizers.model_fit.FittedModelOptimizer`:
    ``(model, center, half_width)``.

    ``model(X, theta)``: ``N x 5`` knobs and ``P`` unknowns -> ``N x 4`` beam on the screen (m).
    The unknowns: :data:`ARES_FITTED_INCOMING` (8), the misalignments q1_x … screen_y (8, m and
    rad), then, unless ``quad_gain_half_width`` is 0, the gains :math:`g_q` of the three
    quadrupoles (:data:`ARES_CALIBRATED_QUADS`, dimensionless): the magnet acts with
    :math:`g_q k_{1,\text{set}}` (a calibration or energy error). ``P = 19`` by default, 16
    without gains. The energy, bunch length and energy spread are held at the middle of their
    ranges. ``center`` and ``half_width``: the middle and half width of the ranges the trials
    were drawn from, and ``1 ± quad_gain_half_width`` (default 0.05) for the gains. With
    ``screen_resolution`` :math:`r_{max}` > 0 (m; default 0: none) one more unknown, the screen's
    resolution :math:`r` in :math:`[0, r_{max}]`: the sizes read are
    :math:`\sqrt{\sigma^2 + r^2}`.
    """
    from pigp_torch.machines.ares_ea.simulation import (
        INCOMING_NAMES,
        KNOB_NAMES,
        AresSegment,
        load_lattice,
    )

    lattice = load_lattice() if lattice is None else lattice
    segment = AresSegment(lattice) if segment is None else segment
    rng = lattice["incoming_beam_ranges"]
    lo = torch.tensor(rng["low"], dtype=DTYPE)
    hi = torch.tensor(rng["high"], dtype=DTYPE)
    order = list(rng["order"])
    if order != list(INCOMING_NAMES):
        raise ValueError(f"lattice incoming-beam order {order} is not {list(INCOMING_NAMES)}")
    if not quad_gain_half_width >= 0:
        raise ValueError(f"quad_gain_half_width must be >= 0, got {quad_gain_half_width}")
    idx = torch.tensor([order.index(n) for n in ARES_FITTED_INCOMING])
    m_lo, m_hi = lattice["misalignments"]["range_m"]
    n_gain = len(ARES_CALIBRATED_QUADS) if quad_gain_half_width > 0 else 0
    n_res = 1 if screen_resolution > 0 else 0
    center = torch.cat(
        [
            (lo + hi)[idx] / 2,
            torch.full((8,), (m_lo + m_hi) / 2, dtype=DTYPE),
            torch.ones(n_gain, dtype=DTYPE),
            torch.full((n_res,), screen_resolution / 2, dtype=DTYPE),
        ]
    )
    half = torch.cat(
        [
            (hi - lo)[idx] / 2,
            torch.full((8,), (m_hi - m_lo) / 2, dtype=DTYPE),
            torch.full((n_gain,), float(quad_gain_half_width), dtype=DTYPE),
            torch.full((n_res,), screen_resolution / 2, dtype=DTYPE),
        ]
    )
    base = (lo + hi) / 2
    quad_idx = [KNOB_NAMES.index(n) for n in ARES_CALIBRATED_QUADS]

    def model(X: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
        inc = base.expand(*theta.shape[:-1], len(INCOMING_NAMES))
        inc = torch.cat([inc[..., :1], theta[..., :8], inc[..., 9:]], dim=-1)
        if n_gain:
            gain = torch.ones(*theta.shape[:-1], len(KNOB_NAMES), dtype=theta.dtype)
            gain = gain.index_copy(-1, torch.tensor(quad_idx), theta[..., 16 : 16 + n_gain])
            X = X * gain  # broadcast as the incoming beam and misalignments are
        out = segment.observe(X, inc, theta[..., 8:16], energy=base[0])
        if not n_res:
            return out
        r = theta[..., -1:]  # broadcast against the rows as theta is
        size = (out[..., [1, 3]].square() + r.square()).sqrt()
        return torch.stack([out[..., 0], size[..., 0], out[..., 2], size[..., 1]], -1)

    return model, center, half


#: Units of the unknowns of :func:`ares_machine_model` (:data:`ARES_FITTED_INCOMING`, then the
#: eight misalignments).
ARES_FITTED_UNITS: tuple[str, ...] = ("m", "rad", "m", "rad", "m", "rad", "m", "rad", *("m",) * 8)


def ares_machine_model(
    target,
    segment=None,
    lattice=None,
    quad_gain_half_width=ARES_QUAD_GAIN_HALF_WIDTH,
    screen_resolution=0.0,
):
    r"""The ARES-EA segment as a :class:`~pigp_torch.prior.machine_model.MachineModel`: the five
    knobs (bidirectional bounds), the four beam numbers on the screen (m), the unknowns of
    :func:`ares_model_parts` (the incoming beam and misalignments with the ranges the trials were
    drawn from, the quadrupoles' gains ``1 ± quad_gain_half_width`` (none with 0) and the screen's
    resolution in ``[0, screen_resolution]`` (none with 0, the default)), and the
    goal :func:`smooth_mae` to ``target`` (``4`` numbers, m) with residual ``o - target``."""
    from pigp_torch.machines.ares_ea.simulation import (
        KNOB_NAMES,
        KNOB_UNITS,
        MISALIGNMENT_NAMES,
        OBSERVABLE_NAMES,
    )
    from pigp_torch.prior.machine_model import MachineModel

    model, center, half = ares_model_parts(
        segment, lattice, quad_gain_half_width, screen_resolution
    )
    res = ("screen_resolution",) if screen_resolution > 0 else ()
    beam = _deblurred if screen_resolution > 0 else None
    gains = tuple(f"{q}_gain" for q in ARES_CALIBRATED_QUADS)[: len(center) - 16 - len(res)]
    t = torch.as_tensor(target, dtype=DTYPE).reshape(-1)
    if t.shape != (4,):
        raise ValueError(f"the ARES target needs 4 numbers (m), got {tuple(t.shape)}")
    return MachineModel(
        name="ares-ea",
        knob_names=KNOB_NAMES,
        knob_units=KNOB_UNITS,
        bounds=knob_bounds(lattice=lattice),
        observable_names=OBSERVABLE_NAMES,
        observable_units=("m",) * 4,
        unknown_names=(*ARES_FITTED_INCOMING, *MISALIGNMENT_NAMES, *gains, *res),
        unknown_units=(*ARES_FITTED_UNITS, *("1",) * len(gains), *("m",) * len(res)),
        unknown_center=center,
        unknown_half_width=half,
        observe=model,
        goal=smooth_mae(t),
        residual=lambda obs: obs - t,
        beam=beam,
    )


def _deblurred(obs: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    r"""The beam behind the screen's reading (``N x 4``, m): the sizes read
    :math:`\sqrt{\sigma^2 + r^2}` back to :math:`\sigma` with the fitted resolution :math:`r` (the
    last unknown); a size read below :math:`r` (a tracked offset can make one) is 0."""
    r2 = theta[..., -1:].square()
    size = (obs[..., [1, 3]].square() - r2).clamp_min(1e-24).sqrt()
    return torch.stack([obs[..., 0], size[..., 0], obs[..., 2], size[..., 1]], -1)


def smooth_mae(target: torch.Tensor, eps: float = 0.5e-6):
    r"""``N x 4 -> N``: :math:`\tfrac14 \sum_i \sqrt{(o_i - t_i)^2 + \epsilon^2}` (m), the mean
    absolute error smoothed below :math:`\epsilon` (default 0.5 µm) so that it has gradients."""
    t = torch.as_tensor(target, dtype=DTYPE)

    def goal(obs: torch.Tensor) -> torch.Tensor:
        return ((obs - t).square() + eps**2).sqrt().mean(-1)

    return goal


def build_ares_physics(
    ctx: RunContext,
    *,
    obs_sd: float | None = None,
    obs_sd_floor: float = 1e-6,
    best_from: str | None = None,
    quad_gain_half_width: float = ARES_QUAD_GAIN_HALF_WIDTH,
    screen_resolution: float = 0.0,
    **options,
):
    r"""``ares-physics``: the ARES model's unknowns fitted online to the screen readings, the next
    setting the fitted model's optimum for the machine's target inside a trust region; once the
    model stops explaining the readings it follows the machine (``fallback="track"``, the
    default): the unknowns, an offset of the four beam numbers and the play of each magnet are
    tracked with forgetting and the tracked model's optimum is asked around the present acting
    fields (:class:`~pigp_torch.optimizers.tracking.TrackingModelOptimizer` of
    :func:`ares_machine_model`, docs/drift_families.md); ``fallback="nm"`` hands the run over to
    Nelder–Mead instead (the former default).

    Args:
        obs_sd: noise of the readings in the fit (m); default ``max(ctx.noise, obs_sd_floor)``
            (``ctx.noise``: the screen noise in m, ``None``: unknown); a larger scatter of the
            repeat readings at the first failed prior check (``noise_probe``, default 2)
            replaces it.
        obs_sd_floor: the smallest noise assumed (default 1 µm).
        best_from: how the best setting is chosen (``"readings"`` or ``"model"``, see
            :class:`FittedModelOptimizer`); default ``"model"`` with a stated screen noise
            (``ctx.noise > 0``), else ``"readings"``.
        quad_gain_half_width: half width of the quadrupoles' fitted gains (default 0.05; 0:
            no gains fitted, the 16 unknowns of the incoming beam and misalignments only).
        screen_resolution: the largest screen resolution fitted (m; default 0: none fitted,
            the sizes read are the beam's; > 0: one more unknown, :func:`ares_model_parts`,
            and the asks put the beam behind the blur on the target, not the reading).
        options: :class:`~pigp_torch.optimizers.tracking.TrackingModelOptimizer` options
            (``fallback``: ``"track"`` by default, ``"nm"`` the hand-over).
    """
    from pigp_torch.optimizers.tracking import TrackingModelOptimizer

    machine = ctx.machine
    target = getattr(machine, "target", None)
    if target is None:
        raise ValueError("ares-physics needs an ARES machine with a target beam")
    if obs_sd is None:
        obs_sd = max(float(ctx.noise or 0.0), float(obs_sd_floor))
    if best_from is None:
        best_from = "model" if (ctx.noise or 0.0) > 0 else "readings"
    options.setdefault("fallback", "track")
    return TrackingModelOptimizer.from_machine_model(
        ares_machine_model(
            target, quad_gain_half_width=quad_gain_half_width, screen_resolution=screen_resolution
        ),
        bounds=ctx.bounds,
        obs_sd=obs_sd,
        best_from=best_from,
        seed=ctx.seed,
        maximize=ctx.maximize,
        **options,
    )


def register_ares_methods(register) -> None:
    """Register ``published-bo``, ``published-nm`` and ``ares-physics`` with ``register`` (the
    method registry's): methods of the ARES-EA linac (``machine="ares-ea"``), in run files on
    ``machine: {kind: ares-sim}`` only."""
    from pigp_torch.methods.registry import MethodSpec
    from pigp_torch.optimizers.model_check import CheckedModelOptimizer
    from pigp_torch.optimizers.model_fit import FittedModelOptimizer
    from pigp_torch.optimizers.tracking import TrackingModelOptimizer

    ares = {"machine": "ares-ea", "run_file": True}
    register(
        MethodSpec(
            "published-bo",
            build_published_bo,
            "gp",
            forwards_to=(PublishedAresBO,),
            fixed=("x0", "seed"),
            **ares,
        )
    )
    register(
        MethodSpec("published-nm", build_published_nm, "direct", forwards_to=(NelderMead,), **ares)
    )
    register(
        MethodSpec(
            "ares-physics",
            build_ares_physics,
            "gp",
            forwards_to=(TrackingModelOptimizer, CheckedModelOptimizer, FittedModelOptimizer),
            fixed=("model", "goal", "theta_center", "theta_half_width", "residual", "seed"),
            **ares,
        )
    )
