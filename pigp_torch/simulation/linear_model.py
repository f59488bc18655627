r"""Fast, batched, differentiable equilibrium-beam model of a ring with thin skew knobs.

The knobs are thin skew quadrupoles, so with every knob at zero the ring is cut at the knobs into
``K + 1`` constant segments. One pyAT ``ohmi_envelope`` pass (knobs at zero) yields, per segment
``s``, its 6×6 transfer matrix :math:`S_s` and the radiation-diffusion matrix :math:`D_s` it adds.
A knob of integrated strength :math:`a` is the linear map :math:`K(a) = I + aE`. For a setting
``x`` the one-turn map and diffusion are chained

.. math::

    M = S_K K_K \cdots K_1 S_0,\qquad
    B \leftarrow K_s B K_s^T,\; B \leftarrow S_s B S_s^T + D_s,

and the equilibrium beam matrix solves the discrete Lyapunov equation :math:`R = M R M^T + B`,
computed by the doubling iteration :math:`R \leftarrow R + A R A^T,\ A \leftarrow A^2`
(:math:`R = \sum_{n < 2^k} M^n B M^{nT}`; well conditioned, unlike :math:`(I - M\otimes M)^{-1}`,
because damping takes thousands of turns).

Observables:

* eigen-emittances: with :math:`R = LL^T`, :math:`RJ` is similar to the real antisymmetric
  :math:`L^T J L`, whose eigenvalues :math:`\pm i\epsilon_k` give the three mode emittances
  (Hermitian eigensolver, distinct eigenvalues, twice differentiable). The largest is the
  longitudinal mode, the middle one εx, the smallest εy.
* beam sizes at the observation points of segment ``s``:
  :math:`\sigma_x^2 = t^T R_s t + d` with :math:`t` the first row of the (fixed) transfer matrix
  from the segment's start, so all σ² are one matrix product of the stacked segment-start beam
  matrices with a precomputed matrix (no per-point propagation).

This is exact within the linearisation that ohmi_envelope itself makes; the only difference to a
full ohmi_envelope with the knobs set is the small closed-orbit change the knobs cause (knobs kick
nothing on the ideal orbit; the radiation sawtooth orbit is ~µm).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

# Symplectic form preserved by pyAT's one-turn matrices in its (x, px, y, py, delta, ct) order.
_J2 = np.array([[0.0, 1.0], [-1.0, 0.0]])
J6 = np.kron(np.eye(3), _J2)


@dataclass
class SegmentModel:
    r"""Precomputed, knob-independent pieces of the ring (all float64 tensors).

    Attributes:
        S: ``(K+1) x 6 x 6`` segment transfer matrices.
        D: ``(K+1) x 6 x 6`` diffusion added by each segment.
        E: ``6 x 6`` derivative of a thin-knob matrix w.r.t. its strength.
        wx, wy: per segment, ``36 x n_s`` maps from the flattened segment-start beam matrix to
            σx², σy² at its ``n_s`` observation points.
        cx, cy: per segment, ``n_s`` diffusion offsets of σx², σy².
        weights: per segment, ``n_s`` length weights of the observation points (sum 1 over ring).
        n_doubling: doubling iterations of the Lyapunov solve.
    """

    S: torch.Tensor
    D: torch.Tensor
    E: torch.Tensor
    wx: list[torch.Tensor]
    wy: list[torch.Tensor]
    cx: list[torch.Tensor]
    cy: list[torch.Tensor]
    weights: list[torch.Tensor]
    n_doubling: int

    @property
    def n_knobs(self) -> int:
        return self.S.shape[0] - 1

    @classmethod
    def from_cumulative(
        cls,
        m66: np.ndarray,
        bbcum: np.ndarray,
        knob_index: list[int],
        obs_index: np.ndarray,
        obs_weight: np.ndarray,
        knob_generator: np.ndarray,
        one_turn: np.ndarray,
    ) -> SegmentModel:
        """Cut the ring at the knobs.

        Args:
            m66: ``(n+1) x 6 x 6`` transfer matrices from the ring start to each element entrance
                (index ``n`` = end of ring), knobs at zero.
            bbcum: ``(n+1) x 6 x 6`` cumulative diffusion matrices, same points.
            knob_index: element indices of the K thin knobs (ascending).
            obs_index: element indices of the observation points.
            obs_weight: their weights.
            knob_generator: ``E`` (6 x 6).
            one_turn: one-turn matrix with knobs at zero (sets the doubling count).
        """
        n = m66.shape[0] - 1
        if list(knob_index) != sorted(knob_index):
            raise ValueError("knob indices must be ascending")
        starts = [0] + [k + 1 for k in knob_index]
        ends = [*knob_index, n]
        inv = {s: np.linalg.inv(m66[s]) for s in starts}
        obs_index = np.asarray(obs_index)
        S, D, wx, wy, cx, cy, ws = [], [], [], [], [], [], []
        for a, b in zip(starts, ends, strict=True):
            seg = m66[b] @ inv[a]
            S.append(seg)
            D.append(bbcum[b] - seg @ bbcum[a] @ seg.T)
            sel = (obs_index >= a) & (obs_index < b)
            j = obs_index[sel]
            T = m66[j] @ inv[a]  # n_s x 6 x 6
            Dj = bbcum[j] - T @ bbcum[a] @ T.transpose(0, 2, 1)
            for row, w_list, c_list in ((0, wx, cx), (2, wy, cy)):
                t = T[:, row, :]
                w_list.append(np.einsum("ni,nj->ijn", t, t).reshape(36, -1))
                c_list.append(Dj[:, row, row])
            ws.append(obs_weight[sel])
        rho = max(abs(np.linalg.eigvals(one_turn)))
        # |M^n| ~ rho^n: enough doublings that rho^(2^k) < 1e-30, three times over for safety
        turns = 3 * 70.0 / max(1.0 - rho, 1e-12)
        n_doubling = math.ceil(math.log2(turns))

        def t(a):
            return torch.as_tensor(np.asarray(a), dtype=torch.float64)

        return cls(
            S=t(np.stack(S)),
            D=t(np.stack(D)),
            E=t(knob_generator),
            wx=[t(a) for a in wx],
            wy=[t(a) for a in wy],
            cx=[t(a) for a in cx],
            cy=[t(a) for a in cy],
            weights=[t(a) for a in ws],
            n_doubling=n_doubling,
        )

    def to(self, device) -> SegmentModel:
        def mv(a):
            return [v.to(device) for v in a] if isinstance(a, list) else a.to(device)

        return SegmentModel(
            **{k: mv(getattr(self, k)) for k in ("S", "D", "E", "wx", "wy", "cx", "cy")},
            weights=mv(self.weights),
            n_doubling=self.n_doubling,
        )


@dataclass
class BeamState:
    """Result of :func:`equilibrium`: per sample, emittances, ⟨1/(σxσy)⟩ and stability."""

    eps: torch.Tensor  # N x 3, ascending: (eps_y, eps_x, eps_z) in m rad
    inv_sigma_xy: torch.Tensor  # N, length-weighted ring average of 1/(sigma_x sigma_y), 1/m^2
    stable: torch.Tensor  # N, bool


def _sandwich(A: torch.Tensor, R: torch.Tensor) -> torch.Tensor:
    return A @ R @ A.transpose(-1, -2)


def _doubling_numpy(M: np.ndarray, B: np.ndarray, n_iter: int):
    """Doubling iteration in numpy (its stacked 6x6 products are ~4x faster than torch.bmm)."""
    R, A = B.copy(), M.copy()
    with np.errstate(over="ignore", invalid="ignore"):  # unstable settings overflow: flagged later
        for _ in range(n_iter):
            R += A @ R @ A.transpose(0, 2, 1)
            A = A @ A
    return 0.5 * (R + R.transpose(0, 2, 1)), np.abs(A).max(axis=(1, 2))


class _Lyapunov(torch.autograd.Function):
    r""":math:`R = M R M^T + B` for stacks of 6x6 matrices on the CPU, differentiable to any order.

    Forward: the doubling iteration in numpy. Backward: the adjoint equation
    :math:`\Lambda = M^T \Lambda M + \bar R`, solved by this same function (so double backward
    works), gives :math:`\bar B = \Lambda` and :math:`\bar M = (\Lambda + \Lambda^T) M R`.
    """

    @staticmethod
    def forward(ctx, M, B, n_iter):
        R, residual = _doubling_numpy(M.detach().numpy(), B.detach().numpy(), n_iter)
        R = torch.from_numpy(R)
        residual = torch.from_numpy(residual)
        ctx.n_iter = n_iter
        ctx.save_for_backward(M, R)
        ctx.mark_non_differentiable(residual)
        return R, residual

    @staticmethod
    def backward(ctx, grad_R, _grad_residual):
        M, R = ctx.saved_tensors
        lam, _ = _Lyapunov.apply(M.transpose(-1, -2), grad_R, ctx.n_iter)
        return (lam + lam.transpose(-1, -2)) @ M @ R, lam, None


def lyapunov_doubling(M: torch.Tensor, B: torch.Tensor, n_iter: int):
    r"""Solve :math:`R = M R M^T + B` (``N x 6 x 6``) by doubling; returns ``(R, residual)``.

    :math:`R = \sum_{n < 2^k} M^n B M^{nT}` with ``k = n_iter``; ``residual`` is
    :math:`\max|M^{2^k}|` per sample: ≈ 0 when the motion is damped, large or non-finite when
    it is not. float64 CPU tensors go through numpy (faster), others through torch.
    """
    if M.device.type == "cpu" and M.dtype == torch.float64:
        return _Lyapunov.apply(M.contiguous(), B.contiguous(), n_iter)
    R, A = B, M
    for _ in range(n_iter):
        R = R + _sandwich(A, R)
        A = A @ A
    return 0.5 * (R + R.transpose(-1, -2)), A.abs().amax(dim=(-1, -2))


def _right(X: torch.Tensor, Wt: torch.Tensor) -> torch.Tensor:
    """``X @ Wt`` for a stack ``X`` (N x 6 x 6) and one fixed 6x6 matrix: one large GEMM."""
    return (X.reshape(-1, 6) @ Wt).view(X.shape)


def _congruence(S: torch.Tensor, B: torch.Tensor) -> torch.Tensor:
    """``S B S^T`` for a fixed S and a stack of SYMMETRIC B (two large GEMMs)."""
    St = S.transpose(0, 1)
    X = _right(B, St)  # B S^T; its transpose is S B
    return _right(X.transpose(1, 2).contiguous(), St)  # (S B) S^T


def _knob(X: torch.Tensor, a: torch.Tensor, Et: torch.Tensor) -> torch.Tensor:
    """``X K^T`` with the thin-knob matrix ``K = I + aE`` (per-sample strength ``a``)."""
    return X + a[:, None, None] * _right(X, Et)


def equilibrium(model: SegmentModel, x: torch.Tensor, *, emittances: bool = True) -> BeamState:
    r"""Equilibrium beam for knob settings ``x`` (``N x K``, float64, any device of the model).

    Unstable settings (no damped equilibrium, or a beam matrix that is not positive definite)
    are flagged in ``stable`` and their outputs set to NaN. With ``emittances=False`` the
    eigen-emittances are skipped (NaN) — the loss rate does not need them.
    """
    N, K = x.shape
    eye = torch.eye(6, dtype=x.dtype, device=x.device)
    Et = model.E.transpose(0, 1)
    # One-turn map (kept transposed: Mt <- Mt S^T is one GEMM) and diffusion, knob by knob.
    Mt = model.S[0].transpose(0, 1).expand(N, 6, 6)
    B = model.D[0].expand(N, 6, 6)
    for s in range(1, K + 1):
        a = x[:, s - 1]
        Mt = _right(_knob(Mt.contiguous(), a, Et), model.S[s].transpose(0, 1))
        B = _knob(B.contiguous(), a, Et)  # B K^T
        B = _knob(B.transpose(1, 2).contiguous(), a, Et)  # K B K^T (symmetric)
        B = _congruence(model.S[s], B) + model.D[s]
    R0, residual = lyapunov_doubling(Mt.transpose(1, 2), B, model.n_doubling)

    stable = torch.isfinite(residual) & (residual < 1e-6)
    # keep unstable rows finite through the rest of the computation, then NaN them at the end
    R0 = torch.where(stable[:, None, None], R0, eye.expand(N, 6, 6))
    L, info = torch.linalg.cholesky_ex(R0)
    stable = stable & (info == 0)
    nan = torch.tensor(float("nan"), dtype=x.dtype, device=x.device)

    if emittances:
        L = torch.where(stable[:, None, None], L, eye.expand(N, 6, 6))
        J = torch.as_tensor(J6, dtype=x.dtype, device=x.device)
        antisym = L.transpose(-1, -2) @ J @ L
        eps = torch.linalg.eigvalsh(1j * antisym.to(torch.complex128))[:, 3:]  # +eps, ascending
        eps = torch.where(stable[:, None], eps, nan)
    else:
        eps = torch.full((N, 3), float("nan"), dtype=x.dtype, device=x.device)

    inv_sig = torch.zeros(N, dtype=x.dtype, device=x.device)
    R = torch.where(stable[:, None, None], R0, eye.expand(N, 6, 6))
    for s in range(K + 1):
        if s > 0:
            R = _congruence(model.S[s - 1], R) + model.D[s - 1]
            R = _knob(R, x[:, s - 1], Et)
            R = _knob(R.transpose(1, 2).contiguous(), x[:, s - 1], Et)
        flat = R.reshape(N, 36)
        sx2 = flat @ model.wx[s] + model.cx[s]
        sy2 = flat @ model.wy[s] + model.cy[s]
        inv_sig = inv_sig + (model.weights[s] * torch.rsqrt(sx2 * sy2)).sum(-1)
    inv_sig = torch.where(stable, inv_sig, nan)
    return BeamState(eps=eps, inv_sigma_xy=inv_sig, stable=stable)
