"""Contract of every acquisition x posterior pair of the Bayesian-optimization core.

The core's :class:`~pigp_torch.optimizers.bo.UCB`, :class:`~pigp_torch.optimizers.bo.EI` and
:class:`~pigp_torch.optimizers.bo.LogEI`, bound to every posterior, equal BoTorch's analytic
``UpperConfidenceBound``, ``ExpectedImprovement`` and ``LogExpectedImprovement`` on the
posterior's BoTorch twin, and so do their gradients (and Hessians, where the posterior gives
them) autograd's of BoTorch's. A new acquisition is one more entry of :data:`PAIRS`.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from botorch.acquisition import (
    ExpectedImprovement,
    LogExpectedImprovement,
    UpperConfidenceBound,
)

from pigp_torch.models._centre_design import expected_information
from pigp_torch.optimizers.bo import (
    EI,
    UCB,
    Alternating,
    CentreInformation,
    CorrelatedCentreInformation,
    ExpectedCentreInformation,
    LogEI,
    Schedule,
)
from tests.contracts.parts import DT, HALF, make_prior, posteriors, readings

PRIOR = make_prior()
X, Y = readings(PRIOR)
POSTERIORS = posteriors(PRIOR, X, Y)
BEST = float(Y.max())

#: acquisition name -> (the core's, BoTorch's on a model)
PAIRS = {
    "ucb": (UCB(2.5), lambda m: UpperConfidenceBound(m, beta=2.5)),
    "ei": (EI(), lambda m: ExpectedImprovement(m, best_f=torch.tensor(BEST, dtype=DT))),
    "logei": (LogEI(), lambda m: LogExpectedImprovement(m, best_f=torch.tensor(BEST, dtype=DT))),
}


def _points(spread: float = 1.0):
    g = torch.Generator().manual_seed(11)
    return (torch.rand(5, X.shape[1], generator=g, dtype=DT) * 2 - 1) * HALF * spread


@pytest.mark.filterwarnings("ignore::botorch.exceptions.warnings.NumericsWarning")
@pytest.mark.parametrize("posterior", sorted(POSTERIORS))
@pytest.mark.parametrize("acq", sorted(PAIRS))
def test_acquisition_equals_botorch(acq, posterior):
    post, twin, _ = POSTERIORS[posterior]
    ours, theirs = PAIRS[acq]
    ref = theirs(twin)
    fun = ours.bind(post, BEST, 1)
    Xs = _points().requires_grad_(True)
    value = ref(Xs.unsqueeze(-2))
    grad = torch.autograd.grad(value.sum(), Xs)[0]
    v, g = fun(Xs.detach().numpy(), 1)
    np.testing.assert_allclose(v, value.detach().numpy(), rtol=1e-7, atol=1e-10)
    np.testing.assert_allclose(g, grad.numpy(), rtol=1e-5, atol=1e-8 * grad.abs().max().item())
    np.testing.assert_array_equal(fun(Xs.detach().numpy(), 0), v)
    if post.max_order < 2:
        return
    _, g2, h = fun(Xs.detach().numpy(), 2)
    np.testing.assert_allclose(g2, g, rtol=1e-12)
    for i in range(Xs.shape[0]):
        hess = torch.autograd.functional.hessian(lambda z: ref(z[None, None])[0], Xs[i].detach())
        np.testing.assert_allclose(h[i], hess.numpy(), rtol=1e-5, atol=1e-7 * hess.abs().max())


def test_logei_stays_finite_far_from_the_data():
    """Where EI underflows to 0, LogEI (ours and BoTorch's) stays finite and equal."""
    post, twin, _ = POSTERIORS["incremental"]
    far = torch.full((1, X.shape[1]), 1.0, dtype=DT)  # ~70 half-ranges away: sigma ~ prior
    fun = LogEI().bind(post, BEST + 5.0, 1)
    ref = LogExpectedImprovement(twin, best_f=torch.tensor(BEST + 5.0, dtype=DT))(far.unsqueeze(-2))
    assert np.isfinite(fun(far.numpy(), 0)).all()
    np.testing.assert_allclose(fun(far.numpy(), 0), ref.detach().numpy(), rtol=1e-9)


def test_centre_information_and_the_schedule():
    """The centre information equals the physics optimizer's torch form, its gradient
    autograd's; :class:`Alternating` picks it every ``every``-th step."""
    post = POSTERIORS["physics"][0]
    info = CentreInformation()
    Xs = _points(0.5).requires_grad_(True)
    model = post.model
    J = model.jacobian(Xs)
    V = J @ model.cov
    Vmu = V[..., : model.dim]
    ref = ((Vmu @ model.shape()) * Vmu).sum(-1) / (model.noise**2 + (V * J).sum(-1))
    grad = torch.autograd.grad(ref.sum(), Xs)[0]
    v, g = info.bind(post, BEST, 0)(Xs.detach().numpy(), 1)
    np.testing.assert_allclose(v, ref.detach().numpy(), rtol=1e-10)
    np.testing.assert_allclose(g, grad.numpy(), rtol=1e-7, atol=1e-9 * grad.abs().max().item())
    sched = Alternating(UCB(), info, 3)
    chosen = []
    for step in range(6):
        sched.bind(post, BEST, step)
        chosen.append(sched.last is info)
    assert chosen == [True, False, False, True, False, False]
    with pytest.raises(ValueError, match="info_every must be >= 0"):
        Alternating(UCB(), info, -1)
    with pytest.raises(ValueError, match="beta must be finite"):
        UCB(-1.0)


def test_written_schedule():
    """:class:`Schedule` ``"uui"`` chooses as :class:`Alternating` with ``every = 3`` (asks 1,
    2, ...); segments with counts come first, the last pattern repeats; bad texts are refused."""
    post = POSTERIORS["physics"][0]
    u, m, i = UCB(), UCB(0.0), CentreInformation()
    alternating, written = Alternating(u, i, 3), Schedule({"u": u, "i": i}, "uui")
    for step in range(1, 13):
        alternating.bind(post, BEST, step)
        written.bind(post, BEST, step)
        assert written.last is alternating.last
    sched = Schedule({"u": u, "m": m, "i": i}, "i@3/um@2/mi")
    assert "".join(sched.letter(k) for k in range(1, 11)) == "iiiummimim"
    x = _points(0.3).numpy()
    np.testing.assert_allclose(sched.bind(post, BEST, 4)(x, 0), u.bind(post, BEST, 4)(x, 0))
    for bad, match in (("uxi", "letters"), ("", "letters"), ("u@2", "no count"),
                       ("u/i", "count >= 1"), ("u@0/i", "count >= 1")):  # fmt: skip
        with pytest.raises(ValueError, match=match):
            Schedule({"u": u, "i": i}, bad)


@pytest.mark.parametrize(
    "acq, rank",
    [(CorrelatedCentreInformation(), 0), (ExpectedCentreInformation(2, 0.5), 2)],
    ids=["correlated", "expected"],
)
def test_early_phase_information(acq, rank):
    """The correlated and the posterior-averaged centre information bound to the physics
    posterior give the model's values (orders 0 and 1) and a gradient equal to central
    differences; both give first derivatives only and refuse bad options."""
    post = POSTERIORS["physics"][0]
    fun = acq.bind(post, BEST, 3)
    assert fun.max_order == 1
    x = _points(0.5).numpy()
    v, g = fun(x, 1)
    ref, _ = expected_information(post.model, x, rank, getattr(acq, "kappa", 1.0))
    np.testing.assert_allclose(v, ref, rtol=1e-12)
    np.testing.assert_array_equal(fun(x, 0), v)
    h = 1e-7
    for k in range(x.shape[1]):
        e = np.zeros(x.shape[1])
        e[k] = h
        np.testing.assert_allclose(g[:, k], (fun(x + e, 0) - fun(x - e, 0)) / (2 * h), rtol=1e-5)
    for bad in ((-1, 1.0), (2, 0.0), (2, float("nan"))):
        with pytest.raises(ValueError, match="rank must be >= 0 and kappa > 0"):
            ExpectedCentreInformation(*bad)
