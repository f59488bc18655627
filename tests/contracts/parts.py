"""Shared fixtures of the contract tests: a physics prior, readings, and BoTorch twins of the
posteriors (the same model as a BoTorch ``Model``, so BoTorch's analytic acquisitions and
autograd give the reference numbers)."""

from __future__ import annotations

import numpy as np
import torch
from botorch.models.model import Model
from botorch.posteriors.gpytorch import GPyTorchPosterior
from gpytorch.distributions import MultivariateNormal

from pigp_torch.models import physics_informed_gp
from pigp_torch.models.botorch_posterior import BoTorchPosterior
from pigp_torch.models.incremental_gp import IncrementalGP, IncrementalPosterior
from pigp_torch.models.physics_posterior import PhysicsFormPosterior
from pigp_torch.prior import PhysicsPrior

DT = torch.float64
D = 3
HALF = 0.015
F_INF = 0.35


def make_prior(noise: float = 0.02) -> PhysicsPrior:
    g = np.random.default_rng(4)
    Q, _ = np.linalg.qr(g.standard_normal((D, D)))
    precision = torch.tensor(Q @ np.diag([2e3, 8e3, 2e4]) @ Q.T, dtype=DT)
    return PhysicsPrior(
        x0=torch.zeros(D, dtype=DT), f_x0=0.9, f_inf=F_INF, precision=precision, amplitude=0.1,
        noise=noise, knob_names=[f"k{i}" for i in range(D)],
        bounds=torch.tensor([[-HALF] * D, [HALF] * D], dtype=DT),
    )  # fmt: skip


def readings(prior: PhysicsPrior, n: int = 9, seed: int = 1):
    """``n`` noisy readings of the physics form centred off the origin (``X: n x d``, ``Y: n``)."""
    g = torch.Generator().manual_seed(seed)
    X = (torch.rand(n, D, generator=g, dtype=DT) * 2 - 1) * HALF
    c = torch.tensor([0.004, -0.003, 0.002], dtype=DT)
    q = ((X - c) @ prior.precision * (X - c)).sum(-1)
    Y = (
        F_INF
        + (0.9 - F_INF) / torch.sqrt(1 + q)
        + prior.noise * torch.randn(n, generator=g, dtype=DT)
    )
    return X, Y.to(DT)


class FormModel(Model):
    """The physics posterior's torch ``predict`` as a BoTorch ``Model`` (independent points)."""

    def __init__(self, model) -> None:
        super().__init__()
        self.form_model = model

    @property
    def num_outputs(self) -> int:
        return 1

    def posterior(self, X, output_indices=None, observation_noise=False, posterior_transform=None):
        mu, sd = self.form_model.predict(X.reshape(-1, X.shape[-1]))
        mean = mu.reshape(X.shape[:-1])
        cov = torch.diag_embed(sd.reshape(X.shape[:-1]) ** 2)
        return GPyTorchPosterior(MultivariateNormal(mean, cov))


def posteriors(prior: PhysicsPrior, X, Y):
    """Every posterior of the core fitted to ``X``, ``Y``, with its BoTorch twin: name ->
    ``(posterior, twin Model, same-as-SingleTaskGP)``."""
    inc = IncrementalPosterior(IncrementalGP(prior.precision, prior.amplitude, prior.noise,
                                             prior.f_inf))  # fmt: skip
    for x, y in zip(X, Y, strict=True):
        inc.observe(x, float(y))
    gp = physics_informed_gp(X, Y, prior)
    bot = BoTorchPosterior(lambda X_, Y_: physics_informed_gp(X_, Y_, prior))
    bot.fit(X, Y)
    phys = PhysicsFormPosterior(prior, prior.bounds, prior_check=False)
    phys.fit(X, Y)
    return {
        "incremental": (inc, gp, True),
        "botorch": (bot, gp, True),
        "physics": (phys, FormModel(phys.model), False),
    }
