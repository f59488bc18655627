r"""The methods, one registry: every optimizer of ``pigp optimize``, the benchmark and Xopt.

:data:`METHODS` maps a name to a :class:`MethodSpec` (builder, budget class, options); each
builder lives in the module of its family and takes a :class:`RunContext`. A new optimizer is
one module with its builder and one :func:`register` call below (a machine kind's own methods:
in the kind's folder).

* ``pigp``: PI-GP BayesOpt, kernel (``kernel``: rbf/rq), mean (``mean``: f_inf/zero/float) and
  noise from the prior; BayesOpt options over :data:`BO_DEFAULTS` (:mod:`~pigp_torch.methods.gp`).
* ``pigp-fast``: the same method on :class:`~pigp_torch.optimizers.fast_bo.FastBayesOpt`
  (:mod:`~pigp_torch.methods.fast`).
* ``pigp-physics``: :class:`~pigp_torch.optimizers.physics_bo.PhysicsModelBO`, the physics form
  fitted online (:mod:`~pigp_torch.methods.physics`); uses the prior's error-ensemble fields
  (``center_cov``, ``peak_shape``) when it has them.
* ``ml2``: BayesOpt with the ML-II diagonal GP (:func:`~pigp_torch.methods.gp.build_ml2`).
* ``nelder-mead``, ``nelder-mead-restart``, ``rcds``: direct methods
  (:mod:`~pigp_torch.methods.direct`).
* ``xopt-ucb``, ``xopt-ucb-travel``, ``xopt-pigp``, ``xopt-tdbo``: through Xopt
  (:mod:`~pigp_torch.methods.xopt`; not in run files).
* the methods of each machine kind (:data:`pigp_torch.machines.KINDS`, registered by
  :meth:`~pigp_torch.machines.MachineKind.register_methods`): ``published-bo``, ``published-nm``,
  the published recipes of the ARES-EA linac task, and ``ares-physics``, its model's unknowns
  fitted online (:mod:`pigp_torch.machines.ares_ea.methods`; in run files on the simulated linac,
  ``machine: {kind: ares-sim}``).
* benchmark variants (not in run files): ``pigp-zero-mean``, ``pigp`` with a zero prior mean
  (Fig. 2c); ``pigp-physics-box``, ``pigp-physics`` with what the model ring alone gives (its own
  shape and the isotropic box prior on the centre, 1 half-range; no error ensemble).

A further variant is one entry: ``register(METHODS["pigp"].with_options(name="pigp-rq",
kernel="rq"))``.
"""

from pigp_torch.machines import KINDS
from pigp_torch.methods.direct import build_nelder_mead, build_nelder_mead_restart, build_rcds
from pigp_torch.methods.fast import build_pigp_fast
from pigp_torch.methods.gp import BO_DEFAULTS, build_ml2, build_pigp
from pigp_torch.methods.physics import build_pigp_physics
from pigp_torch.methods.registry import (
    DEFAULT_BUDGETS,
    METHODS,
    MethodSpec,
    RunContext,
    method_options,
    register,
    resolve_methods,
    run_file_methods,
)
from pigp_torch.methods.xopt import (
    TRAVEL_FRACTION,
    build_xopt_pigp,
    build_xopt_tdbo,
    build_xopt_ucb,
)
from pigp_torch.models.inverse_sqrt import InverseSqrtPeakModel
from pigp_torch.models.physics_posterior import PhysicsFormPosterior
from pigp_torch.optimizers import BayesOpt, NelderMead
from pigp_torch.optimizers.fast_bo import FastBayesOpt
from pigp_torch.optimizers.nm_restart import NelderMeadRestart
from pigp_torch.optimizers.physics_bo import PhysicsModelBO

_BO = {"forwards_to": (BayesOpt,), "fixed": ("model", "seed")}

register(MethodSpec("pigp", build_pigp, "gp", needs_prior=True, run_file=True, **_BO))
register(
    MethodSpec(
        "pigp-fast",
        build_pigp_fast,
        "gp",
        needs_prior=True,
        run_file=True,
        forwards_to=(FastBayesOpt,),
        fixed=("precision", "amplitude", "noise", "seed"),
    )
)
register(
    MethodSpec(
        "pigp-physics",
        build_pigp_physics,
        "gp",
        uses_center_ensemble=True,
        needs_prior=True,
        run_file=True,
        forwards_to=(PhysicsModelBO, PhysicsFormPosterior, InverseSqrtPeakModel),
        fixed=("prior", "seed", "center_cov", "shape"),
    )
)
register(
    MethodSpec(
        "ml2",
        build_ml2,
        "gp",
        run_file=True,
        offline_options=("archive_spread", "learn_noise"),
        **_BO,
    )
)
register(
    MethodSpec("nelder-mead", build_nelder_mead, "direct", run_file=True, forwards_to=(NelderMead,))
)
register(
    MethodSpec(
        "nelder-mead-restart",
        build_nelder_mead_restart,
        "direct",
        run_file=True,
        forwards_to=(NelderMeadRestart, NelderMead),
    )
)
register(MethodSpec("rcds", build_rcds, "direct", run_file=True))
register(MethodSpec("xopt-ucb", build_xopt_ucb, "gp"))
# benchmark variants (not in run files)
register(MethodSpec("pigp-zero-mean", build_pigp, "gp", {"mean": "zero"}))
register(
    MethodSpec(
        "pigp-physics-box",
        build_pigp_physics,
        "gp",
        {"center_prior": "box", "shape_prior": "model"},
    )
)
register(
    MethodSpec("xopt-ucb-travel", build_xopt_ucb, "gp", {"max_travel_distances": TRAVEL_FRACTION})
)
register(MethodSpec("xopt-pigp", build_xopt_pigp, "gp"))
register(MethodSpec("xopt-tdbo", build_xopt_tdbo, "gp"))
# the methods of each machine kind (ARES-EA: published-bo, published-nm, ares-physics)
for _kind in KINDS.values():
    _kind.register_methods(register)

__all__ = [
    "BO_DEFAULTS",
    "DEFAULT_BUDGETS",
    "METHODS",
    "TRAVEL_FRACTION",
    "MethodSpec",
    "RunContext",
    "build_ml2",
    "build_nelder_mead",
    "build_nelder_mead_restart",
    "build_pigp",
    "build_pigp_fast",
    "build_pigp_physics",
    "build_rcds",
    "build_xopt_pigp",
    "build_xopt_tdbo",
    "build_xopt_ucb",
    "method_options",
    "register",
    "resolve_methods",
    "run_file_methods",
]
