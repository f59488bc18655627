r"""An average of independently trained surrogates: a lower-variance Hessian for the prior.

The prior needs the CURVATURE of :math:`t = \log(\hat f - f_\infty)` at the optimum, and the
curvature of one trained network varies from training seed to training seed more than its values
do (13 knobs, 100k samples of the SPEAR3-like ring: 4–7 % relative Frobenius error of the Hessian
for single networks, 3.5 % for the average of three). The ensemble averages :math:`t`:

.. math:: t(x) = \frac1K \sum_k t_k(x),\qquad \hat f(x) = f_\infty + e^{t(x)},

so its Hessian is exactly the mean of the members' Hessians.
"""

from __future__ import annotations

import torch
from torch import nn

from pigp_torch.surrogate.mlp import SurrogateMLP
from pigp_torch.surrogate.train import train_surrogate


class SurrogateEnsemble(nn.Module):
    r"""Mean of the log-excess of several :class:`SurrogateMLP` members on the same knobs.

    Args:
        members: surrogates with identical bounds and :math:`f_\infty`.
    """

    def __init__(self, members) -> None:
        super().__init__()
        members = list(members)
        if not members:
            raise ValueError("an ensemble needs at least one member")
        first = members[0]
        for m in members[1:]:
            if not isinstance(m, SurrogateMLP):
                raise ValueError(f"members must be SurrogateMLP, got {type(m).__name__}")
            if not torch.equal(m.bounds, first.bounds) or float(m.f_inf) != float(first.f_inf):
                raise ValueError("ensemble members must share the knob bounds and f_inf")
        self.members = nn.ModuleList(members)

    @property
    def dim(self) -> int:
        return self.members[0].dim

    @property
    def bounds(self) -> torch.Tensor:
        return self.members[0].bounds

    @property
    def f_inf(self) -> torch.Tensor:
        return self.members[0].f_inf

    @property
    def config(self) -> dict:
        return {"n_members": len(self.members), "member": self.members[0].config}

    def log_excess(self, x) -> torch.Tensor:
        r""":math:`t(x)`, the mean of the members' :math:`\log(\hat f_k - f_\infty)`."""
        return torch.stack([m.log_excess(x) for m in self.members]).mean(0)

    def forward(self, x) -> torch.Tensor:
        r"""Loss rate :math:`f_\infty + e^{t(x)}` (``N x d`` -> ``N``, or ``d`` -> scalar)."""
        t = self.log_excess(x)
        return self.f_inf.to(t.dtype) + torch.exp(t)


def train_ensemble(data, *, n_members: int = 3, seed: int = 0, **kwargs):
    """Train ``n_members`` surrogates with seeds ``seed, seed+1, ...`` (own splits and inits).

    Keyword arguments go to :func:`~pigp_torch.surrogate.train_surrogate`.

    Returns:
        ``(ensemble, reports)``: the ensemble and one report per member.
    """
    if n_members < 1:
        raise ValueError(f"n_members must be >= 1, got {n_members}")
    models, reports = [], []
    for k in range(n_members):
        model, report = train_surrogate(data, seed=seed + k, **kwargs)
        models.append(model)
        reports.append(report)
    return SurrogateEnsemble(models).double().eval(), reports
