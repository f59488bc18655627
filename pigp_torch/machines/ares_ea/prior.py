r"""The paper's physics prior on the ARES-EA task, from the segment's differentiable model.

The GP methods that need a physics prior (``pigp``, ``pigp-fast``: :data:`ARES_PRIOR_METHODS`)
run on ARES with the prior of :func:`~pigp_torch.prior.machine_model.prior_from_machine_model`
of :func:`~.methods.ares_machine_model` for the trial's target: the model's
optimum :math:`x_0` for the target at the unknowns' centre (the middle of the ranges the trials
were drawn from; a trial's own incoming beam and misalignments are never used), the autograd
Hessian of :math:`\log(g_\infty - g)` there (:math:`g` the model's smoothed MAE to the target,
in µm here) as the kernel's precision, and :math:`f_\infty = -g_\infty` as the prior mean.

The prior describes the peak of :math:`f = -g`, a maximized objective, so these methods read
the machine's ``"neg-mae-um"`` objective (:data:`ARES_PRIOR_OBJECTIVE`): minus the MAE of the
four beam numbers to the target, in µm (in m, the GP's noise variance would fall below
GPyTorch's smallest fixed noise, 1e-6, and be rounded up to it). The prior's noise is the
standard deviation of that MAE for a screen noise :math:`\sigma` per number (m):
:math:`10^6 \sigma / 2` µm (the mean of four independent errors, far from the target), and at
least :data:`PRIOR_NOISE_FLOOR_UM`.
"""

from __future__ import annotations

import dataclasses
import functools

import torch

from pigp_torch._utils import DTYPE
from pigp_torch.methods import MethodSpec
from pigp_torch.prior.machine_model import prior_from_machine_model

#: The methods needing a physics prior that run on ARES (the GP with the prior's kernel, mean
#: and noise). ``pigp-physics`` is not among them: its inverse-square-root peak form is the
#: storage ring's loss rate, not a beam's distance to a target.
ARES_PRIOR_METHODS: tuple[str, ...] = ("pigp", "pigp-fast")
#: The machine objective the methods of :data:`ARES_PRIOR_METHODS` read (maximized, µm).
ARES_PRIOR_OBJECTIVE = "neg-mae-um"
#: Smallest noise standard deviation of the prior (µm of MAE), also for a noise-free screen.
PRIOR_NOISE_FLOOR_UM = 1.0
#: µm per m.
_UM = 1e6
#: Draws of the unknowns for the prior's ``center_cov``, for methods that read it.
ARES_PRIOR_ENSEMBLE = 16


def uses_ares_prior(spec: MethodSpec) -> bool:
    """Whether ``spec`` runs on ARES with :func:`ares_prior` (one of :data:`ARES_PRIOR_METHODS`
    that needs a prior)."""
    return spec.needs_prior and spec.name in ARES_PRIOR_METHODS


def prior_noise(screen_noise: float) -> float:
    r"""The prior's noise (µm of MAE) for a screen noise ``screen_noise`` (m per beam number):
    :math:`\max(10^6 \sigma / 2, \text{floor})` (module docstring)."""
    return max(_UM * float(screen_noise) / 2.0, PRIOR_NOISE_FLOOR_UM)


def ares_prior(target, screen_noise: float = 0.0, *, n_ensemble: int = 0):
    r"""The physics prior (:class:`~pigp_torch.prior.PhysicsPrior`, knob units, objective
    :math:`-\mathrm{MAE}` in µm) of the ARES model for ``target`` (``4`` numbers, m): module
    docstring. ``n_ensemble > 0`` adds ``center_cov`` from that many draws of the unknowns.

    Cached per (target, noise, ensemble) in this process: a search for the model's optimum takes
    seconds, and every method of a trial shares the prior.
    """
    key = tuple(float(v) for v in target.reshape(-1).tolist())
    return _cached_prior(key, prior_noise(screen_noise), int(n_ensemble))


@functools.lru_cache(maxsize=8)
def _cached_prior(target: tuple[float, ...], noise: float, n_ensemble: int):
    return prior_from_machine_model(ares_model_um(target), noise=noise, n_ensemble=n_ensemble)


def ares_model_um(target):
    """:func:`~.methods.ares_machine_model` for ``target`` (``4`` numbers, m) with
    its goal (the smoothed MAE) in µm; knobs, observables and unknowns unchanged."""
    from pigp_torch.machines.ares_ea.methods import ares_machine_model

    model = ares_machine_model(torch.as_tensor(target, dtype=DTYPE).reshape(-1))
    goal_m = model.goal
    return dataclasses.replace(model, goal=lambda obs: _UM * goal_m(obs), goal_unit="um")
