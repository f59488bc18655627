r"""NumPy fast paths and box analysis of :class:`~pigp_torch.models.InverseSqrtPeakModel`.

Mixins of the model (kept in their own module to keep each file short): the closed-form
prediction with gradients and the centre information in NumPy (the acquisition search calls them
hundreds of times an ask on ``k x d`` arrays, where each torch call costs more than its
arithmetic), the optimum of the form inside the knob box and its regret metric, and the negative
log posterior of the fit with its gradient in NumPy.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg
import scipy.optimize
import torch
from torch import Tensor

from pigp_torch._utils import DTYPE


class BoxAnalysis:
    """The form's optimum inside the knob box and the metric of a centre error there."""

    def box_optimum(self, tol: float = 1e-9) -> tuple[Tensor, Tensor]:
        r"""The form's maximizer inside the knob box and which knobs sit on a bound there.

        :math:`\hat{\mathbf x} = \arg\min_{\mathbf x \in \text{box}} (\mathbf x -
        \hat{\boldsymbol\mu})^\top B (\mathbf x - \hat{\boldsymbol\mu})`, the projection of
        the fitted centre onto the box in the metric of :math:`B` (:math:`c` and :math:`\beta` do
        not move it): :math:`\hat{\boldsymbol\mu}` itself when it lies inside. Solved exactly as
        a bounded least-squares problem (``scipy.optimize.lsq_linear``, BVLS). Returns
        ``(x_hat, active)``, ``active`` a boolean ``d`` mask of the knobs at a bound with the
        form still rising outward (relative tolerance ``tol`` of the half-range)."""
        mu = self.center()
        inside = (mu >= self.bounds[0]) & (mu <= self.bounds[1])
        if bool(inside.all()):
            return mu, torch.zeros(self.dim, dtype=torch.bool)
        B = self.shape()
        A = torch.linalg.cholesky(B).T.numpy()  # B = L L^T: minimize |L^T (x - mu)|^2
        res = scipy.optimize.lsq_linear(
            A, A @ mu.numpy(), bounds=(self.bounds[0].numpy(), self.bounds[1].numpy()),
            method="bvls", tol=1e-12,
        )  # fmt: skip
        x = torch.from_numpy(res.x).to(DTYPE)
        grad = B @ (x - mu)  # half the quadratic's gradient: > 0 at a lower bound (< 0 at an
        # upper one) means the unconstrained minimum lies beyond that bound
        slack = tol * (self.bounds[1] - self.bounds[0]) / 2
        active = ((x <= self.bounds[0] + slack) & (grad > 0)) | (
            (x >= self.bounds[1] - slack) & (grad < 0)
        )
        return x, active

    def regret_metric(self) -> Tensor:
        r"""``d x d`` matrix :math:`M` with which an error :math:`\boldsymbol\delta` of the
        fitted centre costs :math:`\tfrac12\,\beta\,g(\hat{\mathbf x})^{-3/2}\,
        \boldsymbol\delta^\top M \boldsymbol\delta` (to second order) at the box optimum
        :math:`\hat{\mathbf x}` of :meth:`box_optimum`.

        With the free knobs :math:`F` and the active ones :math:`A` (fixed at their bound), the
        box optimum is :math:`\hat{\mathbf x}_F = \boldsymbol\mu_F - B_{FF}^{-1} B_{FA}
        (\mathbf b_A - \boldsymbol\mu_A)`, so :math:`P = \partial\hat{\mathbf x}_F /
        \partial\boldsymbol\mu = [I \;\; B_{FF}^{-1}B_{FA}]`, and the loss on the face is
        quadratic with Hessian :math:`\beta g^{-3/2} B_{FF}` (the gradient of :math:`g`
        vanishes along the face): :math:`M = P^\top B_{FF} P`, which is
        :math:`B` less the Schur complement :math:`B_{AA} - B_{AF}B_{FF}^{-1}B_{FA}` in the
        active block (how far the centre lies beyond the face does not matter). Inside the box
        :math:`M = B`."""
        B = self.shape()
        _, active = self.box_optimum()
        if not bool(active.any()):
            return B
        F = ~active
        M = B.clone()
        BAA = B[active][:, active]
        if bool(F.any()):
            BAF = B[active][:, F]
            schur = BAA - BAF @ torch.linalg.solve(B[F][:, F], BAF.T)
        else:
            schur = BAA
        idx = active.nonzero().squeeze(-1)
        M[idx.unsqueeze(-1), idx] -= schur
        return M


class NumpyPrediction:
    """Closed-form prediction, gradients and centre information in NumPy."""

    def predict_with_grad(self, X: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        r""":meth:`predict` and its gradients in ``X`` in closed form (no autograd graph):
        ``(mu, sd, dmu, dsd)``, ``n``, ``n``, ``n x d``, ``n x d``.

        With :math:`\mathbf D = \mathbf x - \hat{\boldsymbol\mu}`, :math:`g = c + \beta
        \mathbf D^\top B\mathbf D` and :math:`\mathbf w = C\,\mathbf j` (:math:`\mathbf j`
        the row of :meth:`jacobian`):

        .. math::
            \nabla f = -\beta g^{-3/2} B\mathbf D, \qquad
            \nabla(\mathbf j^\top C\mathbf j) = 2 \sum_k w_k \nabla j_k,

        :math:`\nabla j_k` from :math:`j_k = -\tfrac12 g^{-3/2}\,\partial g/\partial\theta_k`
        (:math:`\nabla g^{-3/2} = -3\beta g^{-5/2} B\mathbf D`). The residual GP adds
        :math:`\nabla k_i = -k_i P(\mathbf x - \mathbf x_i)` to the mean (weights
        :math:`\alpha`) and :math:`-2\sum_i u_i \nabla k_i`, :math:`\mathbf u = K^{-1}\mathbf
        k`, to the variance; :math:`\nabla\sigma = \nabla\sigma^2 / (2\sigma)` (zero where the
        variance sits at its floor).

        Computed in NumPy from the fit's quantities (cached once per fit): the acquisition
        search calls this hundreds of times an ask on ``k x d`` arrays of a few starts, where
        each torch call costs more than its arithmetic. A test checks it against autograd of
        :meth:`predict`."""
        out = self.predict_numpy(X.detach().numpy())
        return tuple(torch.from_numpy(np.ascontiguousarray(a)) for a in out)

    def predict_numpy(self, x: np.ndarray) -> tuple[np.ndarray, ...]:
        """:meth:`predict_with_grad` on and to NumPy arrays: ``(mu, sd, dmu, dsd)`` at ``n x d``
        settings ``x``."""
        st = self._prediction_state()
        pt = self._form_terms(st, x)
        beta, BD = st["beta"], pt["BD"]
        mu = st["background"] + pt["g"] ** -0.5
        dmu = (2.0 * pt["dfdg"])[..., None] * beta * BD
        J = pt["J"]
        W = J @ st["cov"]  # n x p
        var = (W * J).sum(-1)
        dvar = 2.0 * self._contract_grad_j(st, pt, W)
        if self.residual_std > 0:
            Dr = x[..., None, :] - st["Xr"]  # n x m x d
            PDr = Dr @ st["P"]
            Ks = self.residual_std**2 * np.exp(-0.5 * (PDr * Dr).sum(-1))  # n x m
            mu = mu + Ks @ st["alpha"]
            dmu = dmu - ((Ks * st["alpha"])[..., None] * PDr).sum(-2)
            Lr = st["L"]  # K = L L^T: U = K^-1 k by two triangular solves
            U = np.swapaxes(_cho_solve(Lr, np.swapaxes(Ks, -1, -2)), -1, -2)
            var = var + self.residual_std**2 - (Ks * U).sum(-1)
            dvar = dvar + 2.0 * ((U * Ks)[..., None] * PDr).sum(-2)
        floor = var <= 1e-18
        sd = np.sqrt(np.maximum(var, 1e-18))
        dsd = np.where(floor[..., None], 0.0, dvar / (2 * sd)[..., None])
        return mu, sd, dmu, dsd

    def _prediction_state(self) -> dict:
        """The fitted quantities of :meth:`predict_with_grad` as NumPy arrays, computed once per
        fit (the cache is keyed on the very tensors of the fit, which a new fit replaces)."""
        theta = self._fitted()
        key = (theta, self.cov, getattr(self, "_L", None), getattr(self, "_X", None))
        cached = getattr(self, "_np_state", None)
        if cached is not None and all(a is b for a, b in zip(cached["key"], key, strict=True)):
            return cached
        d = self.dim
        st = {
            "key": key,
            "mu": theta[:d].numpy(),
            "B": self.shape(theta).numpy(),
            "c": float(torch.exp(theta[d])),
            "beta": float(torch.exp(theta[d + 1])),
            "background": float(self.background(theta)),
            "cov": self.cov.numpy(),
        }
        if self.shape_std > 0:
            st["V"] = self._V.numpy()
            st["lam"] = (self._lam * torch.exp(theta[self._s_index : self._s_index + d])).numpy()
        if self.residual_std > 0:
            st["Xr"], st["P"] = self._X.numpy(), self._res_prec.numpy()
            st["alpha"], st["L"] = self._alpha.numpy(), self._L.numpy()
        self._np_state = st
        return st

    def _form_terms(self, st: dict, x: np.ndarray) -> dict:
        r"""The form's pieces at ``n x d`` settings ``x`` (NumPy, fitted :math:`\theta` from
        ``st``): :math:`\mathbf D`, :math:`B\mathbf D`, :math:`q`, :math:`g`,
        :math:`\partial f/\partial g = -\tfrac12 g^{-3/2}`, :math:`\mathbf D^\top V` (shape
        fitted) and the ``n x p`` rows :math:`J` of :meth:`jacobian`."""
        c, beta = st["c"], st["beta"]
        D = x - st["mu"]
        BD = D @ st["B"]
        q = (BD * D).sum(-1)
        g = c + beta * q
        dfdg = -0.5 * g**-1.5
        cols = [-2.0 * beta * BD, np.broadcast_to(c, q.shape)[..., None], (beta * q)[..., None]]
        J = np.concatenate(cols, -1) * dfdg[..., None]
        if self.f_inf_std > 0:
            J = np.concatenate([J, np.ones_like(q)[..., None]], -1)
        DV = None
        if self.shape_std > 0:
            DV = D @ st["V"]
            J = np.concatenate([J, (beta * DV**2 * st["lam"]) * dfdg[..., None]], -1)
        return {"D": D, "BD": BD, "q": q, "g": g, "dfdg": dfdg, "DV": DV, "J": J}

    def _contract_grad_j(self, st: dict, pt: dict, A: np.ndarray) -> np.ndarray:
        r""":math:`\sum_k a_k \nabla_{\mathbf x} j_k` for ``n x p`` weights ``A`` (one row per
        setting), ``n x d``: with :math:`j_k = \tfrac{\partial f}{\partial g}
        \tfrac{\partial g}{\partial\theta_k}`, :math:`\nabla (\partial f/\partial g) =
        \tfrac32\beta g^{-5/2} B\mathbf D` and the gradients of :math:`\partial
        g/\partial\theta_k` (:math:`-2\beta B` for the centre, :math:`2\beta B\mathbf D` for
        :math:`\log\beta`, :math:`2\beta\lambda_k e^{s_k}(\mathbf v_k^\top\mathbf D)\mathbf
        v_k` for a shape log-scale; none for :math:`\log c` and the background)."""
        d, c, beta = self.dim, st["c"], st["beta"]
        BD, q, g, DV = pt["BD"], pt["q"], pt["g"], pt["DV"]
        # sum_k a_k dg/dtheta_k, then the same with each dg/dtheta_k differentiated in x
        adg = -2.0 * beta * (A[..., :d] * BD).sum(-1) + A[..., d] * c + A[..., d + 1] * beta * q
        inner = -2.0 * beta * (A[..., :d] @ st["B"]) + (2.0 * beta * A[..., d + 1])[..., None] * BD
        if self.shape_std > 0:
            i = self._s_index
            As = A[..., i : i + d]
            adg = adg + (As * beta * DV**2 * st["lam"]).sum(-1)
            inner = inner + 2.0 * beta * ((As * st["lam"] * DV) @ st["V"].T)
        return (adg * 1.5 * beta * g**-2.5)[..., None] * BD + pt["dfdg"][..., None] * inner

    def centre_information_with_grad(self, X: Tensor) -> tuple[Tensor, Tensor]:
        r"""How much one more reading at each of ``n x d`` settings shrinks
        :math:`\mathrm{tr}(B\,C_\mu)`, :math:`C_\mu` the Laplace covariance of the fitted
        centre, and its ``n x d`` gradient in closed form.

        With :math:`\mathbf j` the row of :meth:`jacobian`, :math:`\mathbf v = C\mathbf j`,
        :math:`N = \mathbf v_\mu^\top B\,\mathbf v_\mu` and :math:`S = \sigma_n^2 +
        \mathbf j^\top C\mathbf j` (Sherman-Morrison), the reduction is :math:`I = N / S` and

        .. math:: \nabla I = \sum_k \bigl(2\,(C_{\cdot\mu} B\,\mathbf v_\mu)_k
                  - 2 I\, v_k\bigr)\,\nabla j_k \,/\, S

        (:meth:`_contract_grad_j`). Units: knob units squared (of the trace), per knob unit
        for the gradient."""
        info, grad = self.centre_information_numpy(X.detach().numpy())
        return torch.from_numpy(info), torch.from_numpy(np.ascontiguousarray(grad))

    def centre_information_numpy(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`centre_information_with_grad` on and to NumPy arrays (``n``, ``n x d``)."""
        st = self._prediction_state()
        pt = self._form_terms(st, x)
        J, cov, d = pt["J"], st["cov"], self.dim
        V = J @ cov
        BVmu = V[..., :d] @ st["B"]
        S = self.noise**2 + (V * J).sum(-1)
        info = (BVmu * V[..., :d]).sum(-1) / S
        A = 2.0 * (BVmu @ cov[:d, :]) - 2.0 * info[..., None] * V
        grad = self._contract_grad_j(st, pt, A) / S[..., None]
        return info, grad


def _cho_solve(L: np.ndarray, b: np.ndarray) -> np.ndarray:
    """:math:`(L L^\top)^{-1} b` for a lower Cholesky factor ``L`` (``m x m``) and ``m x k``
    ``b``."""
    y = scipy.linalg.solve_triangular(L, b, lower=True, check_finite=False)
    return scipy.linalg.solve_triangular(L.T, y, lower=False, check_finite=False)
