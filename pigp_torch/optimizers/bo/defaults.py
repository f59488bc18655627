"""The defaults of the Bayesian-optimization recipes, in one place.

The recipe classes (:class:`~pigp_torch.optimizers.BayesOpt`,
:class:`~pigp_torch.optimizers.FastBayesOpt`, :class:`~pigp_torch.optimizers.PhysicsModelBO`)
take their keyword defaults from here and the registered methods
(:mod:`pigp_torch.methods`) build them with these, so a class and its method agree.
"""

#: Shared by the GP recipes (``pigp``, ``ml2`` on :class:`BayesOpt`; ``pigp-fast``): UCB with
#: :math:`\beta = 4` (the authors' :math:`\mu + 2\sigma`), a trust box of half-width 0.3 of each
#: knob's half-range around the best noisy reading; ``optimize_acqf`` with 4 L-BFGS-B restarts
#: from 128 Sobol points.
BO_DEFAULTS = {
    "acquisition": "ucb",
    "beta": 4.0,
    "step_limit": 0.3,
    "trust_center": "best_observed",
    "num_restarts": 4,
    "raw_samples": 128,
}

#: The Newton search of :class:`FastBayesOpt` (``pigp-fast``): the 10 best of 256 random points
#: (plus the box centre and the last two proposals) are climbed.
NEWTON_SEARCH_DEFAULTS = {"num_restarts": 10, "raw_samples": 256}

#: :class:`PhysicsModelBO` (``pigp-physics``): UCB with :math:`\beta = 4`, trust box of half-width
#: 0.6 around the told point of highest posterior mean, 8 Sobol starts of the multi-start
#: L-BFGS-B, the centre-information ask every third ask; while following a drift the UCB with
#: :math:`\beta = 1` (:math:`\mu + \sigma`) at every ask (``track_schedule``, ``track_beta``).
PHYSICS_DEFAULTS = {
    "beta": 4.0,
    "step_limit": 0.6,
    "n_starts": 8,
    "info_every": 3,
    "track_schedule": "w",
    "track_beta": 1.0,
}
