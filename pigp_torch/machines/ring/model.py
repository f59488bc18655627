r"""A storage ring as a :class:`~pigp_torch.prior.machine_model.MachineModel`.

The simulated ring (:class:`~pigp_torch.machines.ring.ring.RingCoupling`, SPEAR3 or any
lattice) is seen through the fast linear model
(:meth:`~pigp_torch.machines.ring.ring.RingCoupling.evaluate`: batched and differentiable in
the knobs):

* **knobs** :math:`x \in \mathbb R^K`: the skew windings (control units, A for SPEAR3), bounds
  the simulator's (±30 A);
* **observables**: the loss rate :math:`f` (mA/min), and behind it the emittances
  :math:`\epsilon_x` (nm) and :math:`\epsilon_y` (pm), in units where each is a number of order
  1–100 (a fit weighs them with one noise level);
* **unknowns** :math:`\theta = (\delta, d, e)`, what a ring's operator does not know:

  - :math:`\delta \in \mathbb R^K`: the coupling errors as the knob setting that would cause them
    (the machine at setting :math:`x` behaves as the model at :math:`x + \delta`), so the machine's
    optimum is the model's moved by :math:`-\delta`; this is the projection of the error pattern
    onto the span of the knobs, the part of it a knob setting can correct (control units, range
    :math:`\pm` ``coupling_half_width``, default a quarter of each knob's limit);
  - :math:`d`: the loss-rate map's relative background (range :math:`0 \pm 0.8`) and :math:`e`:
    its relative Touschek scale (:math:`0 \pm 0.3`): :math:`f = f_\infty (1 + d) + g (1 + e)
    \langle 1/(\sigma_x\sigma_y)\rangle` (vacuum, current and fill pattern set them; no lattice
    model knows them; the benchmark draws its machines' from :math:`d \in [-0.8, 0.3]`,
    :math:`e \in [-0.3, 0.3]`);

* **goal**: :math:`-f` (the loss rate maximized: the larger the beam, the longer it lives), with
  background :math:`g_\infty(\theta) = -f_\infty (1 + d)`.

At the centre of the unknowns (:math:`\delta = 0, d = e = 0`) ``observe`` is the model ring's own
``evaluate``, so the paper's prior of this model is the one the benchmark computes from
:meth:`~pigp_torch.machines.ring.ring.RingCoupling.loss_rate`.
"""

from __future__ import annotations

import torch
from torch import Tensor

from pigp_torch._utils import DTYPE
from pigp_torch.prior.machine_model import MachineModel

#: Observables of the ring's model and their units.
RING_OBSERVABLES: tuple[str, ...] = ("loss_rate", "eps_x", "eps_y")
RING_OBSERVABLE_UNITS: tuple[str, ...] = ("mA/min", "nm", "pm")
#: The simulator's emittances (m) in :data:`RING_OBSERVABLE_UNITS`.
_EPS_SCALE: tuple[float, float] = (1e9, 1e12)
#: Centre and half width of the loss-rate map's relative background ``d`` and scale ``e``.
LOSS_MAP_CENTER: tuple[float, float] = (0.0, 0.0)
LOSS_MAP_HALF_WIDTH: tuple[float, float] = (0.8, 0.3)


def ring_machine_model(sim, coupling_half_width: float | Tensor | None = None) -> MachineModel:
    r"""The ring ``sim`` (:class:`~pigp_torch.machines.ring.ring.RingCoupling`) as a
    machine model (module docstring).

    Args:
        sim: the model ring (its error seed is the model's, not the machine's).
        coupling_half_width: half width of the knob-equivalent coupling errors :math:`\delta`
            (control units; one value or ``K``); default a quarter of each knob's limit.

    Returns:
        A :class:`~pigp_torch.prior.machine_model.MachineModel` with ``K`` knobs, 3 observables
        and ``K + 2`` unknowns; ``observe(X, theta)`` takes ``N x K`` settings and ``P`` (or
        ``N x P``) unknowns and returns ``N x 3`` (NaN rows where the ring has no stable beam).

    Raises:
        ValueError: a non-positive ``coupling_half_width``.
    """
    K = sim.dim
    limits = sim.bounds[1].to(DTYPE)
    if coupling_half_width is None:
        half_delta = limits / 4
    else:
        half_delta = torch.as_tensor(coupling_half_width, dtype=DTYPE).expand(K).clone()
    f_inf = float(sim.loss_rate_map[0])
    unit = sim.knob_units

    def observe(X: Tensor, theta: Tensor) -> Tensor:
        theta = torch.as_tensor(theta, dtype=DTYPE)
        out = sim.evaluate(torch.as_tensor(X, dtype=DTYPE) + theta[..., :K])
        d, e = theta[..., K], theta[..., K + 1]
        loss = f_inf * (1 + d) + (1 + e) * (out.loss_rate - f_inf)
        eps_x, eps_y = out.eps_x * _EPS_SCALE[0], out.eps_y * _EPS_SCALE[1]
        return torch.stack([loss, eps_x, eps_y], dim=-1)

    return MachineModel(
        name=f"ring {sim.name}",
        knob_names=sim.knob_names,
        knob_units=[unit] * K,
        bounds=sim.bounds,
        observable_names=RING_OBSERVABLES,
        observable_units=RING_OBSERVABLE_UNITS,
        unknown_names=[*(f"{n}_error" for n in sim.knob_names), "loss_background", "loss_scale"],
        unknown_units=[unit] * K + ["1", "1"],
        unknown_center=torch.cat([torch.zeros(K, dtype=DTYPE), torch.tensor(LOSS_MAP_CENTER)]),
        unknown_half_width=torch.cat([half_delta, torch.tensor(LOSS_MAP_HALF_WIDTH)]),
        observe=observe,
        goal=lambda O: -O[..., 0],
        goal_unit="mA/min",
        goal_background=lambda theta: -f_inf * (1 + float(theta[K])),
    )
