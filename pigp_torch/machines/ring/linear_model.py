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

* eigen-emittances from symplectic invariants (:func:`eigen_emittances`): the eigenvalues of
  :math:`RJ` are :math:`\pm i\epsilon_k`; :math:`\mathrm{tr}(RJ)^2`,
  :math:`\mathrm{tr}(R^{-1}J)^2` and :math:`\det R` give the cubic whose roots are
  :math:`\epsilon_k^2`, solved in closed form (no batched eigensolver). The largest is the
  longitudinal mode, the middle one εx, the smallest εy.
* beam sizes at the observation points of segment ``s``:
  :math:`\sigma_x^2 = t^T R_s t + d` with :math:`t` the first row of the (fixed) transfer matrix
  from the segment's start, so all σ² of a segment are one matrix product of the flattened
  segment-start beam matrices with a precomputed ``36 x 2n_s`` matrix (no per-point propagation).

Speed (why the code looks the way it does; the benchmark that times each choice is
:mod:`~pigp_torch.machines.ring.throughput`):

* every product with a *fixed* matrix is one large GEMM: the congruence :math:`S R S^T` is
  ``vec(R) @ (S ⊗ S)^T`` (36×36; faster than two 6×6 products plus a transpose copy);
* a knob touches two rows/columns (:math:`E` has two entries), so :math:`K X K^T` is four
  row/column updates instead of matrix products;
* per-sample 6×6 products (the doubling) go through numpy on the CPU (its stacked 6×6 ``matmul``
  is faster than ``torch.bmm``) and through ``torch.matmul`` on other devices;
* the doubling count comes from the damping of the knobs-off ring (:math:`2^k (1-\rho) \ge 32`),
  not from a fixed worst case;
* without autograd, updates are in place (no large temporaries);
* :func:`equilibrium_chunked` evaluates 2k-row chunks (cache-sized) on several threads.

This is exact within the linearisation that ohmi_envelope itself makes; the only difference to a
full ohmi_envelope with the knobs set is the small closed-orbit change the knobs cause (knobs kick
nothing on the ideal orbit; the radiation sawtooth orbit is ~µm).
"""

from __future__ import annotations

import contextlib
import math
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
import torch

from pigp_torch.machines.ring.lyapunov import eigen_emittances, lyapunov_doubling

#: doublings until M^(2^k) has decayed by e^-32 at the knobs-off damping (|M^2^k| ~ 1e-14)
DAMPING_EXPONENT = 32.0
#: a setting is "damped" when max|M^(2^k)| is below this (truncation error of R ~ its square)
RESIDUAL_TOL = 1e-6
#: beam matrix substituted in unstable rows so the math stays finite (eigen-emittances 1, 2, 3)
_SAFE_DIAG = (1.0, 1.0, 2.0, 2.0, 3.0, 3.0)


@dataclass
class SegmentModel:
    r"""Precomputed, knob-independent pieces of the ring (all float64 tensors).

    Attributes:
        S: ``(K+1) x 6 x 6`` segment transfer matrices.
        D: ``(K+1) x 6 x 6`` diffusion added by each segment.
        E: ``6 x 6`` derivative of a thin-knob matrix w.r.t. its strength.
        w_obs: per segment, ``36 x 2n_s`` map from the flattened segment-start beam matrix to
            ``[σx² | σy²]`` at its ``n_s`` observation points (before the offsets).
        c_obs: per segment, ``2n_s`` diffusion offsets of ``[σx² | σy²]``.
        weights: per segment, ``n_s`` length weights of the observation points (sum 1 over ring).
        n_doubling: doubling iterations of the Lyapunov solve.

    Derived on construction: ``kron`` (``(K+1) x 36 x 36``, ``vec(R) @ kron[s] = vec(S_s R
    S_s^T)``), ``St`` (the transposed ``S``) and ``knob_terms`` (the non-zeros of ``E``).
    """

    S: torch.Tensor
    D: torch.Tensor
    E: torch.Tensor
    w_obs: list[torch.Tensor]
    c_obs: list[torch.Tensor]
    weights: list[torch.Tensor]
    n_doubling: int
    kron: torch.Tensor = field(init=False, repr=False)
    St: torch.Tensor = field(init=False, repr=False)
    knob_terms: tuple = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.St = self.S.transpose(1, 2).contiguous()
        self.kron = torch.stack([torch.kron(s, s).T.contiguous() for s in self.S])
        E = self.E.detach().cpu()
        terms = tuple((int(i), int(j), float(E[i, j])) for i, j in E.nonzero().tolist())
        written, read = {i for i, _, _ in terms}, {j for _, j, _ in terms}
        if written & read:  # a thin skew quadrupole has E[1,2] = E[3,0] = 1: disjoint
            raise ValueError(
                "knob generator E must not read the rows it writes (E @ E = 0 structure); "
                f"non-zeros at {[(i, j) for i, j, _ in terms]}"
            )
        self.knob_terms = terms

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
        S, D, w_obs, c_obs, ws = [], [], [], [], []
        for a, b in zip(starts, ends, strict=True):
            seg = m66[b] @ inv[a]
            S.append(seg)
            D.append(bbcum[b] - seg @ bbcum[a] @ seg.T)
            sel = (obs_index >= a) & (obs_index < b)
            j = obs_index[sel]
            T = m66[j] @ inv[a]  # n_s x 6 x 6
            Dj = bbcum[j] - T @ bbcum[a] @ T.transpose(0, 2, 1)
            # sigma_row^2 = t^T R t + Dj[row, row] = vec(R) . vec(t t^T) + offset
            w = [np.einsum("ni,nj->ijn", T[:, r], T[:, r]).reshape(36, -1) for r in (0, 2)]
            w_obs.append(np.concatenate(w, axis=1))
            c_obs.append(np.concatenate([Dj[:, 0, 0], Dj[:, 2, 2]]))
            ws.append(obs_weight[sel])
        return cls(
            S=_t(np.stack(S)),
            D=_t(np.stack(D)),
            E=_t(knob_generator),
            w_obs=[_t(a) for a in w_obs],
            c_obs=[_t(a) for a in c_obs],
            weights=[_t(a) for a in ws],
            n_doubling=doubling_count(one_turn),
        )

    def to(self, device) -> SegmentModel:
        """A copy with every tensor on ``device``."""

        def mv(a):
            return [v.to(device) for v in a] if isinstance(a, list) else a.to(device)

        return SegmentModel(
            **{k: mv(getattr(self, k)) for k in ("S", "D", "E", "w_obs", "c_obs", "weights")},
            n_doubling=self.n_doubling,
        )


def _t(a) -> torch.Tensor:
    return torch.as_tensor(np.asarray(a), dtype=torch.float64)


def doubling_count(one_turn: np.ndarray, exponent: float = DAMPING_EXPONENT) -> int:
    r"""Doublings ``k`` with :math:`2^k (1 - \rho) \ge` ``exponent``, :math:`\rho` = max |eig|.

    Then :math:`|M^{2^k}| \approx e^{-\text{exponent}}` and the truncated tail of
    :math:`R = \sum_n M^n B M^{nT}` is :math:`\approx e^{-2\,\text{exponent}}` relative. With the
    default 32 a setting whose slowest damping rate is half the knobs-off one still has residual
    ≈ e^-16 < :data:`RESIDUAL_TOL` (tail ≈ 1e-14); below ~0.43 of it the setting is flagged
    unstable. Skew knobs only share damping between x and y (Robinson's sum is fixed), so in
    practice the rate barely moves inside the knob box.
    """
    rho = float(max(abs(np.linalg.eigvals(one_turn))))
    if not rho < 1 - 1e-12:
        raise ValueError(f"the knobs-off ring is not damped (max |eigenvalue| = {rho})")
    return max(1, math.ceil(math.log2(exponent / (1.0 - rho))))


@dataclass
class BeamState:
    """Result of :func:`equilibrium`: per sample, emittances, ⟨1/(σxσy)⟩ and stability."""

    eps: torch.Tensor  # N x 3, ascending: (eps_y, eps_x, eps_z) in m rad
    inv_sigma_xy: torch.Tensor  # N, length-weighted ring average of 1/(sigma_x sigma_y), 1/m^2
    stable: torch.Tensor  # N, bool

    @staticmethod
    def cat(states: list[BeamState]) -> BeamState:
        """Concatenate the rows of several states (chunked evaluation)."""
        if len(states) == 1:
            return states[0]
        return BeamState(*(torch.cat([getattr(s, k) for s in states]) for k in _STATE_FIELDS))


_STATE_FIELDS = ("eps", "inv_sigma_xy", "stable")


# ----------------------------------------------------------------------------- knob updates
def _knob_rows(X: torch.Tensor, a: torch.Tensor, E, inplace: bool) -> torch.Tensor:
    """``K X`` with ``K = I + aE``.

    In place: row i += a E[i,j] row j for the non-zeros of ``E`` (``E`` is then the tuple
    ``knob_terms``; rows read are never written). Otherwise ``X + a (E X)`` (``E`` a tensor):
    three autograd nodes instead of views and in-place updates (faster Hessians).
    """
    if not inplace:
        return X + a[:, :, None] * (E @ X)
    for i, j, v in E:
        X[:, i].addcmul_(X[:, j], a, value=v)
    return X


def _knob_cols(X: torch.Tensor, a: torch.Tensor, E, inplace: bool) -> torch.Tensor:
    """``X K^T``: column i += a E[i,j] column j (in place), else ``X + a (X E^T)``."""
    if not inplace:
        return X + a[:, :, None] * (X @ E.T)
    for i, j, v in E:
        X[:, :, i].addcmul_(X[:, :, j], a, value=v)
    return X


def _congruence(R: torch.Tensor, kron_t: torch.Tensor, D: torch.Tensor) -> torch.Tensor:
    """``S R S^T + D`` for a stack R as one GEMM: ``vec(R) @ (S ⊗ S)^T + vec(D)``."""
    N = R.shape[0]
    return torch.addmm(D.reshape(36), R.reshape(N, 36), kron_t).view(N, 6, 6)


# ----------------------------------------------------------------------------- the model
def equilibrium(
    model: SegmentModel, x: torch.Tensor, *, emittances: bool = True, torch_only: bool = False
) -> BeamState:
    r"""Equilibrium beam for knob settings ``x`` (``N x K``, float64, any device of the model).

    Unstable settings (no damped equilibrium, or a beam matrix that is not positive definite)
    are flagged in ``stable`` and their outputs set to NaN. With ``emittances=False`` the
    eigen-emittances are skipped (NaN) — the loss rate does not need them. Differentiable in
    ``x`` to any order (the prior's Hessian goes through here); without autograd the updates run
    in place. Every operation runs on ``x``'s device; ``torch_only=True`` also keeps the CPU off
    numpy (the exact code path of a GPU, for testing it without one).
    """
    N, K = x.shape
    if K != model.n_knobs:
        raise ValueError(f"x must have {model.n_knobs} columns (one per knob), got {K}")
    inplace = not (torch.is_grad_enabled() and x.requires_grad)
    terms = model.knob_terms if inplace else model.E
    # One-turn map (kept transposed: Mt <- Mt K^T S^T is one GEMM) and diffusion, knob by knob.
    Mt = model.St[0].expand(N, 6, 6).clone()
    B = model.D[0].expand(N, 6, 6).clone()
    for s in range(1, K + 1):
        a = x[:, s - 1 : s]
        Mt = _knob_cols(Mt, a, terms, inplace)
        Mt = (Mt.reshape(-1, 6) @ model.St[s]).view(N, 6, 6)
        B = _knob_cols(_knob_rows(B, a, terms, inplace), a, terms, inplace)
        B = _congruence(B, model.kron[s], model.D[s])
    R0, residual = lyapunov_doubling(Mt.transpose(1, 2), B, model.n_doubling, torch_only=torch_only)

    stable = torch.isfinite(residual) & (residual < RESIDUAL_TOL)
    # keep unstable rows finite (and away from degenerate roots) through the rest, NaN at the end
    safe = torch.diag(torch.tensor(_SAFE_DIAG, dtype=x.dtype, device=x.device))
    R = torch.where(stable[:, None, None], R0, safe)
    L, info = torch.linalg.cholesky_ex(R)
    if not bool((info == 0).all()):
        stable = stable & (info == 0)
        R = torch.where(stable[:, None, None], R, safe)
        L = torch.linalg.cholesky_ex(R)[0]  # finite everywhere (also for the backward pass)
    nan = torch.tensor(float("nan"), dtype=x.dtype, device=x.device)

    if emittances:
        eps = torch.where(stable[:, None], eigen_emittances(R, L), nan)
    else:
        eps = torch.full((N, 3), float("nan"), dtype=x.dtype, device=x.device)

    inv_sig = torch.zeros(N, dtype=x.dtype, device=x.device)
    for s in range(K + 1):
        if s > 0:
            R = _congruence(R, model.kron[s - 1], model.D[s - 1])
            a = x[:, s - 1 : s]
            R = _knob_cols(_knob_rows(R, a, terms, inplace), a, terms, inplace)
        n_s = model.weights[s].shape[0]
        sig2 = torch.addmm(model.c_obs[s], R.reshape(N, 36), model.w_obs[s])  # [sx^2 | sy^2]
        if inplace:
            prod = sig2[:, :n_s].mul_(sig2[:, n_s:]).rsqrt_()
            inv_sig.addmv_(prod, model.weights[s])
        else:
            inv_sig = inv_sig + torch.rsqrt(sig2[:, :n_s] * sig2[:, n_s:]) @ model.weights[s]
    inv_sig = torch.where(stable, inv_sig, nan)
    return BeamState(eps=eps, inv_sigma_xy=inv_sig, stable=stable)


def equilibrium_chunked(
    model: SegmentModel,
    x: torch.Tensor,
    *,
    chunk: int,
    emittances: bool = True,
    workers: int = 1,
) -> BeamState:
    """:func:`equilibrium` on ``chunk``-row pieces of ``x``, on ``workers`` threads.

    Small chunks keep the stacks of 6x6 matrices in cache (on 2 CPU cores 2k-row chunks beat
    16k-row ones). ``workers > 1`` evaluates chunks concurrently (torch and numpy release the
    GIL in their kernels; torch's own intra-op threads are set to 1 meanwhile and restored, so
    the cores are not oversubscribed). Threads are only used without autograd.
    """
    if chunk < 1 or workers < 1:
        raise ValueError(f"chunk and workers must be >= 1, got {chunk} and {workers}")
    pieces = [x[i : i + chunk] for i in range(0, x.shape[0], chunk)] or [x]

    def one(piece):
        return equilibrium(model, piece, emittances=emittances)

    grad = torch.is_grad_enabled() and x.requires_grad
    if workers == 1 or len(pieces) == 1 or grad or x.device.type != "cpu":
        return BeamState.cat([one(p) for p in pieces])
    with _single_threaded_torch(), ThreadPoolExecutor(min(workers, len(pieces))) as pool:
        return BeamState.cat(list(pool.map(_no_grad(one), pieces)))


_THREADS_LOCK = threading.Lock()
_THREADS_STATE = {"active": 0, "saved": 1}


@contextlib.contextmanager
def _single_threaded_torch():
    """torch intra-op threads = 1 inside; the first caller in saves, the last one out restores.

    (A plain save/set/restore would leave torch at 1 thread when two callers overlap.)
    """
    with _THREADS_LOCK:
        if _THREADS_STATE["active"] == 0:
            _THREADS_STATE["saved"] = torch.get_num_threads()
            torch.set_num_threads(1)
        _THREADS_STATE["active"] += 1
    try:
        yield
    finally:
        with _THREADS_LOCK:
            _THREADS_STATE["active"] -= 1
            if _THREADS_STATE["active"] == 0:
                torch.set_num_threads(_THREADS_STATE["saved"])


def _no_grad(fn):
    """Run ``fn`` under ``torch.no_grad`` (grad mode is thread-local: set it in the worker)."""

    def wrapped(*args):
        with torch.no_grad():
            return fn(*args)

    return wrapped
