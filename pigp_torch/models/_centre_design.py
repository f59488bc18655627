r"""Centre information for the early phase of a run: the exact correlated update, and its
average over the posterior of the form's parameters.

:meth:`~pigp_torch.models.InverseSqrtPeakModel.centre_information_numpy` treats one more reading
as independent of the told ones. The residual GP says otherwise: the readings' errors have the
covariance :math:`\Sigma = K + \sigma_n^2 I` (:math:`K` the residual kernel at the told
settings, the fit's precision), and a reading next to a told one repeats part of what that one
said. With :math:`G` the ``m x p`` Jacobian of the form at the told settings and
:math:`\Lambda_0` the prior precision of :math:`\theta`, the Laplace precision of the readings
is :math:`A = G^\top\Sigma^{-1}G + \Lambda_0` (covariance :math:`C = A^{-1}`). One more reading
at :math:`\mathbf x` (cross-covariance :math:`\mathbf k(\mathbf x)` with the told ones, Jacobian
row :math:`\mathbf j`) adds, by the block inverse of the extended :math:`\Sigma`,

.. math::
    \mathbf u = \mathbf j - G^\top\Sigma^{-1}\mathbf k, \qquad
    s^2 = \sigma_n^2 + k(\mathbf x, \mathbf x) - \mathbf k^\top\Sigma^{-1}\mathbf k, \qquad
    A' = A + \mathbf u\mathbf u^\top / s^2,

so (Sherman-Morrison) :math:`\mathrm{tr}(B\,C_\mu)` falls by

.. math:: I(\mathbf x) = \frac{(C\mathbf u)_\mu^\top B\,(C\mathbf u)_\mu}{s^2 + \mathbf u^\top
          C\mathbf u}

(knob units squared). Without a residual GP (:math:`\mathbf k = 0`, :math:`\Sigma =
\sigma_n^2 I`) this is the independent information.

Averaged over the posterior (``rank > 0``): early in a run the fitted :math:`\hat\theta` is
biased and :math:`I` at :math:`\hat\theta` places the reading for a centre that is not there.
The expected reduction :math:`\mathrm E_\theta[I(\mathbf x;\theta)]` over the Laplace
posterior :math:`\mathcal N(\hat\theta, C)` is taken with unscented sigma points along the
``rank`` directions in which the centre's uncertainty costs most: the leading eigenvectors
:math:`\mathbf w_k` of :math:`S^\top B S` (:math:`C_{\mu\mu} = SS^\top`), i.e. the
one-standard-deviation centre errors :math:`\boldsymbol\delta_k = S\mathbf w_k` of largest
:math:`\boldsymbol\delta^\top B\boldsymbol\delta`, moved with the other parameters' regression
on the centre, :math:`\boldsymbol\Delta_k = C_{\cdot\mu}C_{\mu\mu}^{-1}\boldsymbol\delta_k`.
The points are :math:`\hat\theta` (weight :math:`\kappa/(r+\kappa)`) and :math:`\hat\theta \pm
\sqrt{r+\kappa}\,\boldsymbol\Delta_k` (weight :math:`1/(2(r+\kappa))` each), which average a
quadratic function of :math:`\theta` in that subspace exactly. At each point the form's
Jacobian, :math:`C` and :math:`B` are recomputed (:math:`\Sigma` stays the fit's).
"""

from __future__ import annotations

import math

import numpy as np
import scipy.linalg
import torch

from pigp_torch._utils import DTYPE
from pigp_torch.models._inverse_sqrt_numpy import _cho_solve


def design_states(model, rank: int = 0, kappa: float = 1.0) -> list[dict]:
    r"""The per-:math:`\theta` states of :func:`expected_information` (cached per fit): the
    fitted :math:`\hat\theta` alone for ``rank = 0``, else its ``2 rank + 1`` sigma points
    (module docstring). Each state has the form's quantities of :meth:`_form_terms` at its
    :math:`\theta`, ``C`` (``p x p``), ``H`` :math:`= \Sigma^{-1}G` (``m x p``) and its weight
    ``w``."""
    if int(rank) < 0 or not (math.isfinite(float(kappa)) and float(kappa) > 0):
        raise ValueError(f"rank must be >= 0 and kappa > 0, got {rank} and {kappa}")
    base = model._prediction_state()
    key = (base["key"], int(rank), float(kappa))
    cached = getattr(model, "_design_cache", None)
    if cached is not None and cached[0][1:] == key[1:]:
        if all(a is b for a, b in zip(cached[0][0], key[0], strict=True)):
            return cached[1]
    Xt = model._X
    prior = model.prior_precision().numpy()
    theta = model._fitted()

    def state(th: torch.Tensor, weight: float) -> dict:
        d = model.dim
        st = {
            "mu": th[:d].numpy(),
            "B": model.shape(th).numpy(),
            "c": float(torch.exp(th[d])),
            "beta": float(torch.exp(th[d + 1])),
            "w": weight,
            "theta": th,
        }
        if model.shape_std > 0:
            st["V"] = base["V"]
            st["lam"] = (model._lam * torch.exp(th[model._s_index : model._s_index + d])).numpy()
        G = model.jacobian(Xt, th).numpy()
        H = _cho_solve(base["L"], G) if model.residual_std > 0 else G / model.noise**2
        st["H"] = H
        st["C"] = scipy.linalg.cho_solve(scipy.linalg.cho_factor(G.T @ H + prior), np.eye(len(G.T)))
        return st

    centre = state(theta, 1.0)
    states = [centre]
    if rank > 0:
        r = min(int(rank), model.dim)
        C, d = centre["C"], model.dim
        S = np.linalg.cholesky(C[:d, :d])
        _, W = np.linalg.eigh(S.T @ centre["B"] @ S)
        W = W[:, ::-1][:, :r]  # leading directions of the centre's cost
        # Delta_k = C[:, mu] C_mumu^-1 S w_k = C[:, mu] S^-T w_k
        Delta = C[:, :d] @ scipy.linalg.solve_triangular(S.T, W, lower=False)
        spread = math.sqrt(r + kappa)
        centre["w"] = kappa / (r + kappa)
        for k in range(r):
            for sign in (1.0, -1.0):
                step = torch.from_numpy(sign * spread * Delta[:, k]).to(DTYPE)
                states.append(state(theta + step, 0.5 / (r + kappa)))
    model._design_cache = (key, states)
    return states


def expected_information(model, x: np.ndarray, rank: int = 0, kappa: float = 1.0):
    r""":math:`\sum_s w_s I(\mathbf x;\theta_s)` over :func:`design_states` (module docstring) at
    ``n x d`` settings ``x``, and its ``n x d`` gradient in closed form: with :math:`\mathbf v =
    C\mathbf u`, :math:`S = s^2 + \mathbf u^\top\mathbf v` and :math:`\mathbf a = 2C_{\cdot\mu}
    B\mathbf v_\mu - 2I\mathbf v`,

    .. math:: S\,\nabla I = \sum_k a_k\nabla j_k + \sum_i \bigl(2I(\Sigma^{-1}\mathbf k)_i -
              (\Sigma^{-1}G\mathbf a)_i\bigr)\nabla k_i,

    :math:`\nabla k_i = -k_i P(\mathbf x - \mathbf x_i)` (:math:`P` the residual kernel's
    precision). Returns ``(info, grad)``, knob units squared (per knob unit for the gradient)."""
    base = model._prediction_state()
    x = np.asarray(x, dtype=np.float64)
    d = model.dim
    residual = model.residual_std > 0
    if residual:
        Dr = x[..., None, :] - base["Xr"]
        PDr = Dr @ base["P"]
        Ks = model.residual_std**2 * np.exp(-0.5 * (PDr * Dr).sum(-1))  # n x m
        U = np.swapaxes(_cho_solve(base["L"], np.swapaxes(Ks, -1, -2)), -1, -2)
        s2 = model.noise**2 + model.residual_std**2 - (Ks * U).sum(-1)
    else:
        s2 = np.full(x.shape[:-1], model.noise**2)
    info = np.zeros(x.shape[:-1])
    grad = np.zeros(x.shape)
    for st in design_states(model, rank, kappa):
        pt = model._form_terms(st, x)
        C, H = st["C"], st["H"]
        u = pt["J"] - Ks @ H if residual else pt["J"]
        v = u @ C
        Bv = v[..., :d] @ st["B"]
        S = s2 + (u * v).sum(-1)
        value = (Bv * v[..., :d]).sum(-1) / S
        A = 2.0 * (Bv @ C[:d, :]) - 2.0 * value[..., None] * v
        g = model._contract_grad_j(st, pt, A)
        if residual:
            coef = 2.0 * value[..., None] * U - A @ H.T  # n x m
            g = g - ((coef * Ks)[..., None] * PDr).sum(-2)
        info += st["w"] * value
        grad += st["w"] * g / S[..., None]
    return info, grad
