"""The Bayesian-optimization core: parts compose freely, recipes are compositions, BoTorch
acquisition objects and new acquisitions plug in."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from botorch.acquisition import ProbabilityOfImprovement

from pigp_torch.models import physics_informed_gp
from pigp_torch.models.incremental_gp import IncrementalGP, IncrementalPosterior
from pigp_torch.optimizers import BayesOpt, FastBayesOpt
from pigp_torch.optimizers.bo import (
    UCB,
    BayesianOptimizer,
    BOParts,
    MultiStartLBFGSB,
    NewtonSearch,
    TrustRegion,
)
from tests.contracts.parts import DT, make_prior, readings

PRIOR = make_prior()
X, Y = readings(PRIOR, n=6)


def _told(opt):
    for x, y in zip(X, Y, strict=True):
        opt.tell(x, float(y))
    return opt


class PosteriorMean:
    """A new acquisition in a few lines: the posterior mean (orders 0 and 1)."""

    name = "mean"

    def bind(self, posterior, best_f, step):
        def fun(X_, order=0):
            p = posterior.predict(X_, order)
            return p.mean if order == 0 else (p.mean, p.dmean)

        return fun


def test_fast_bayesopt_is_the_core_with_its_parts():
    """A hand-built BayesianOptimizer of the same parts asks the same points to the bit."""
    fast = _told(FastBayesOpt.from_prior(PRIOR.bounds, PRIOR, seed=3))
    gp = IncrementalGP(PRIOR.precision, PRIOR.amplitude, PRIOR.noise, PRIOR.f_inf)
    parts = BOParts(IncrementalPosterior(gp), UCB(4.0), NewtonSearch(10, 256),
                    TrustRegion(PRIOR.bounds, 0.3))  # fmt: skip
    core = _told(BayesianOptimizer(PRIOR.bounds, parts, seed=3))
    for _ in range(3):
        a, b = fast.ask(), core.ask()
        assert torch.equal(a, b)
        fast.tell(a, 0.5)
        core.tell(b, 0.5)


def test_parts_compose_beyond_the_recipes():
    """The incremental GP with the multi-start L-BFGS-B search and a new acquisition: proposals
    stay in the trust box and climb the posterior mean."""
    gp = IncrementalGP(PRIOR.precision, PRIOR.amplitude, PRIOR.noise, PRIOR.f_inf)
    region = TrustRegion(PRIOR.bounds, 0.5, "best_mean")
    opt = _told(BayesianOptimizer(PRIOR.bounds, BOParts(IncrementalPosterior(gp), PosteriorMean(),
                                                        MultiStartLBFGSB(4), region)))  # fmt: skip
    x = opt.ask()
    info = opt.last_info
    assert bool(((x >= info["trust_lower"]) & (x <= info["trust_upper"])).all())
    mean_at = opt.parts.posterior.predict(np.stack([x.numpy(), info["center"].numpy()]), 0).mean
    assert mean_at[0] >= mean_at[1] - 1e-12  # at least the centre's mean
    assert info["acq_value"] == pytest.approx(mean_at[0], rel=1e-12)


def test_a_new_acquisition_plugs_into_fast_bayesopt():
    opt = _told(FastBayesOpt.from_prior(PRIOR.bounds, PRIOR, acquisition=PosteriorMean()))
    x = opt.ask()
    assert opt.acquisition == "mean" and opt.last_info["solver"] == "lbfgsb"  # no Hessian
    assert opt.last_info["acq_value"] == pytest.approx(float(opt.posterior(x)[0][0]), rel=1e-12)


def test_a_botorch_acquisition_object_is_used_as_it_is():
    """BayesOpt with BoTorch's ProbabilityOfImprovement: its value at the proposal is the
    reported one, and the proposal lies in the trust box."""

    def factory(X_, Y_):
        return physics_informed_gp(X_, Y_, PRIOR)

    def make(model, best_f):
        return ProbabilityOfImprovement(model, best_f=best_f)

    opt = _told(BayesOpt(PRIOR.bounds, factory, acquisition=make, num_restarts=2,
                         raw_samples=32, seed=1))  # fmt: skip
    x = opt.ask()
    pi = make(opt.last_model, torch.tensor(float(Y.max()), dtype=DT))(x[None, None])
    assert opt.last_info["acq_value"] == pytest.approx(float(pi), rel=1e-9)
    assert bool(((x >= opt.last_info["trust_lower"]) & (x <= opt.last_info["trust_upper"])).all())
    with pytest.raises(ValueError, match="acquisition must be"):
        BayesOpt(PRIOR.bounds, factory, acquisition=3)
