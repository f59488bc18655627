r"""``RingCoupling``: vertical emittance and Touschek loss rate of any storage ring vs skew knobs.

A machine = a radiating pyAT ring + thin skew-quadrupole knobs + the coupling errors of one seed
(:mod:`~pigp_torch.machines.ring.errors`), scaled so that with every knob at zero
εy/εx = ``target_ratio``.

Knobs are set in **control units** (amps of a skew winding's power supply, by default); inside the
physics a knob of value :math:`I` is a thin skew quadrupole of integrated strength

.. math:: K_{1s}L = c\,I \qquad (c = \text{knob calibration, 1/m per control unit}).

A knob is named by an element of the ring: a thin ``at.ThinMultipole`` is used as it is; a thick
sextupole, quadrupole or multipole is split in two halves with a thin winding (named after the
knob) between them. Names are a family name that occurs once, ``FAM[n]`` (the ``n``-th element of
family ``FAM``, from 0), or ``#i`` (the element of index ``i``).

Loss-rate proxy. The Touschek rate scales as ⟨1/(σx σy σz)⟩ around the ring; σz does not depend on
the skew knobs, so the proxy is ⟨1/(σx σy)⟩ (length-weighted over elements), mapped linearly to
mA/min:

.. math::

    \text{loss\_rate} = f_\infty + g\,\langle 1/(\sigma_x\sigma_y)\rangle .

``(f∞, g)`` is the ``loss_rate_map``; by default it is calibrated once per lattice and knob set so
that error seed 1 has 0.5 mA/min with the knobs at zero and 1.7 mA/min at its optimum, with a
background f∞ of at least SPEAR3's share (19.6 %) of the knobs-off rate; where the knobs cannot
raise ⟨1/(σxσy)⟩ that far (a few knobs), the optimum is lower than 1.7 mA/min
(:func:`calibrate_loss_rate_map`). Every loss rate is then positive.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import at
import numpy as np
import torch

from pigp_torch._utils import DTYPE, as_knob_tensor
from pigp_torch._utils.multistart import find_optimum
from pigp_torch.machines.ring import errors as _errors
from pigp_torch.machines.ring import reference as _ref
from pigp_torch.machines.ring.calibration import calibrate_error_scale, calibrate_loss_rate_map
from pigp_torch.machines.ring.lattice import fingerprint, insert_knobs, load_ring
from pigp_torch.machines.ring.linear_model import SegmentModel, equilibrium_chunked

TARGET_RATIO = 0.0071  # skews-off eps_y / eps_x
CHUNK = 2048  # rows per CPU evaluation (cache-sized)
GPU_CHUNK = 1 << 19  # rows per batched evaluation on other devices (~8 GB of float64 buffers)
#: error seed and (knobs-off, optimum) loss rates (mA/min) that define the default loss-rate map
LOSS_RATE_ANCHOR = (1, 0.5, 1.7)


class CouplingResult(NamedTuple):
    """Observables of one or N settings (tensors of shape ``()`` or ``N``).

    Attributes:
        eps_x: horizontal mode emittance (m rad).
        eps_y: vertical mode emittance (m rad).
        loss_rate: Touschek loss-rate proxy (mA/min).
        stable: ``False`` where the setting has no stable equilibrium (then the others are NaN).
    """

    eps_x: torch.Tensor
    eps_y: torch.Tensor
    loss_rate: torch.Tensor
    stable: torch.Tensor


# ---------------------------------------------------------------------- one machine
_BASES: dict = {}


def _base(ring: at.Lattice, knobs: tuple[str, ...]) -> dict:
    key = (fingerprint(ring), knobs)
    if key not in _BASES:
        base, index = insert_knobs(ring, knobs)
        _BASES[key] = {"ring": base, "knob_index": index, "key": key}
    return _BASES[key]


@functools.lru_cache(maxsize=64)
def _machine(base_key, error_seed: int, target_ratio: float, scale) -> dict:
    """Apply the errors of one seed, calibrate their scale, precompute the fast model (cached)."""
    base = _BASES[base_key]
    ring0 = base["ring"]
    pattern = _errors.CouplingErrors.draw(error_seed, *_errors.magnet_counts(ring0))
    if scale is None:
        scale = calibrate_error_scale(ring0, pattern, target_ratio)
    ring = ring0.deepcopy()
    pattern.apply(ring, scale)
    knob_index = list(base["knob_index"])
    order = np.argsort(knob_index)
    obs_index, obs_weight = _ref.observation_points(ring)
    cum = _ref.cumulative_matrices(ring)
    model = SegmentModel.from_cumulative(
        cum["m66"],
        cum["bbcum"],
        [knob_index[i] for i in order],
        obs_index,
        obs_weight,
        _ref.thin_knob_generator(),
        cum["one_turn"],
    )
    return {
        "ring": ring,
        "scale": float(scale),
        "knob_index": knob_index,
        "order": torch.as_tensor(order),
        "obs": (obs_index, obs_weight),
        "model": model,
    }


class RingCoupling:
    r"""A simulated storage ring whose εy and Touschek loss rate respond to skew knobs.

    Args:
        lattice: the ideal ring: an ``at.Lattice``, a shipped deck name, a JSON element table or
            any lattice file pyAT loads (see :func:`load_ring`).
        knobs: knob names (``FAM``, ``FAM[n]`` or ``#i``; see the module docstring).
        knob_calibration: K1s·L (1/m) per control unit, one value or one per knob.
        knob_limit: symmetric bound of each knob in control units, one value or one per knob.
        knob_units: name of the control unit (default ``"A"``).
        error_seed: seed of the coupling-error pattern (one "machine" per seed).
        target_ratio: knobs-off εy/εx that the error scale is calibrated to (default 0.71 %).
        error_scale: use this global error scale instead of calibrating (1 = nominal rms).
        loss_rate_map: ``(f_inf [mA/min], g [mA/min m²])``; default: calibrated on error seed 1
            of the same lattice and knobs (:func:`calibrate_loss_rate_map`).
        energy: beam energy (eV) where the lattice source carries none (default 3 GeV).
        name: a label for reprs and provenance records.

    Knob values are float64 tensors ``(N, K)`` or ``(K,)`` in control units. Building a machine
    (knob insertion, error calibration, one ohmi_envelope pass) is cached per process.

    Raises:
        ValueError: bad knobs, calibration or limits, ``target_ratio`` outside (0, 1), or a
            non-positive ``error_scale``.
        RuntimeError: the error scale cannot be calibrated for this seed.
    """

    def __init__(
        self,
        lattice,
        knobs,
        knob_calibration,
        *,
        knob_limit=30.0,
        knob_units: str = "A",
        error_seed: int = 1,
        target_ratio: float = TARGET_RATIO,
        error_scale: float | None = None,
        loss_rate_map: tuple[float, float] | None = None,
        energy: float | None = None,
        name: str | None = None,
    ) -> None:
        if not (0 < target_ratio < 1):
            raise ValueError(f"target_ratio must be in (0, 1), got {target_ratio}")
        if error_scale is not None and not error_scale > 0:
            raise ValueError("error_scale must be positive (an error-free ring has εy = 0)")
        ring = load_ring(lattice, energy=energy)
        self.knob_names = [str(n) for n in knobs]
        self.knob_units = str(knob_units)
        k = len(self.knob_names)
        self.knob_calibration = _per_knob(knob_calibration, k, "knob_calibration")
        self.knob_limits = _per_knob(knob_limit, k, "knob_limit")
        self.error_seed = int(error_seed)
        self.target_ratio = float(target_ratio)
        self.name = name or str(getattr(ring, "name", "") or "ring")
        self._base = _base(ring, tuple(self.knob_names))
        self._m = _machine(self._base["key"], self.error_seed, self.target_ratio, error_scale)
        self.error_scale = self._m["scale"]
        if loss_rate_map is None:
            loss_rate_map = _default_map(self._base["key"], self.target_ratio, self._calibrations)
        self.loss_rate_map = (float(loss_rate_map[0]), float(loss_rate_map[1]))
        self._models = {}
        self._optimum = None
        #: the :class:`~pigp_torch.machines.ring.spec.RingSpec` this machine was built from, if any
        self.spec = None

    @property
    def _calibrations(self) -> tuple:
        return tuple(float(c) for c in self.knob_calibration)

    # ------------------------------------------------------------------ properties
    @property
    def dim(self) -> int:
        """Number of knobs K."""
        return len(self.knob_names)

    @property
    def knob_limit(self) -> float:
        """The largest knob bound (control units); :attr:`bounds` has each knob's own."""
        return float(self.knob_limits.max())

    @property
    def bounds(self) -> torch.Tensor:
        """``2 x K`` knob bounds (control units)."""
        lim = self.knob_limits.clone()
        return torch.stack([-lim, lim])

    @property
    def loss_background(self) -> float:
        """f(∞): the loss rate approached when the beam gets very large (mA/min)."""
        return self.loss_rate_map[0]

    @property
    def lattice(self) -> at.Lattice:
        """A copy of this machine's pyAT lattice (errors applied, knobs at zero)."""
        return self._m["ring"].deepcopy()

    @property
    def ideal_lattice(self) -> at.Lattice:
        """A copy of the ideal ring with the knobs' thin windings inserted (no errors)."""
        return self._base["ring"].deepcopy()

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}({self.name!r}, error_seed={self.error_seed}, "
            f"knobs={self.dim}, error_scale={self.error_scale:.4f})"
        )

    def k1sl(self, x) -> torch.Tensor:
        """Integrated skew strengths K1s·L (1/m) of knob settings ``x`` (control units)."""
        X, single = as_knob_tensor(x, self.dim)
        out = X * self.knob_calibration.to(X.device)
        return out[0] if single else out

    # ------------------------------------------------------------------ evaluation
    def _model(self, device) -> SegmentModel:
        key = str(device)
        if key not in self._models:
            self._models[key] = self._m["model"].to(device)
        return self._models[key]

    def _equilibrium(self, X: torch.Tensor, *, emittances: bool, workers: int | None = None):
        """The fast model on ``X`` (``N x K`` control units): chunked, threaded on the CPU."""
        K = X * self.knob_calibration.to(X.device)
        Ko = K[:, self._m["order"].to(X.device)]
        cpu = X.device.type == "cpu"
        return equilibrium_chunked(
            self._model(X.device),
            Ko,
            chunk=CHUNK if cpu else GPU_CHUNK,
            emittances=emittances,
            workers=(workers or torch.get_num_threads()) if cpu else 1,
        )

    def evaluate(self, x) -> CouplingResult:
        r"""Fast batched model: εx, εy and the loss rate at knob settings ``x``.

        Args:
            x: ``K`` or ``N x K`` knob settings (control units). Differentiable: gradients flow
                back to ``x`` when it requires grad. Runs on ``x``'s device.

        Returns:
            :class:`CouplingResult`; rows without a stable equilibrium have ``stable=False`` and
            NaN observables (never a silent finite value).

        Raises:
            ValueError: wrong shape or NaN/inf entries.
        """
        X, single = as_knob_tensor(x, self.dim)
        state = self._equilibrium(X, emittances=True)
        f_inf, gain = self.loss_rate_map
        out = CouplingResult(
            eps_x=state.eps[:, 1],
            eps_y=state.eps[:, 0],
            loss_rate=f_inf + gain * state.inv_sigma_xy,
            stable=state.stable,
        )
        return CouplingResult(*(v[0] for v in out)) if single else out

    def inv_sigma_xy(self, x) -> torch.Tensor:
        """⟨1/(σxσy)⟩ (1/m², length-weighted ring average) at ``x`` (differentiable)."""
        X, single = as_knob_tensor(x, self.dim)
        out = self._equilibrium(X, emittances=False).inv_sigma_xy
        return out[0] if single else out

    def loss_rate(self, x) -> torch.Tensor:
        """``evaluate(x).loss_rate``, skipping the eigen-emittances (differentiable; for priors)."""
        f_inf, gain = self.loss_rate_map
        return f_inf + gain * self.inv_sigma_xy(x)

    def reference(self, x) -> CouplingResult:
        """The same observables from pyAT ``ohmi_envelope`` with the knobs set (slow: one envelope
        computation each)."""
        X, single = as_knob_tensor(x, self.dim)
        ring = self._m["ring"].deepcopy()
        f_inf, gain = self.loss_rate_map
        rows = []
        for ki in self.k1sl(X).detach().cpu().numpy():
            _ref.set_knobs(ring, self._m["knob_index"], ki)
            try:
                eps, inv_sig = _ref.envelope_at(ring, *self._m["obs"])
                ok = bool(np.all(np.isfinite(eps)) and np.isfinite(inv_sig))
            except Exception:  # pyAT raises when there is no closed orbit / stable motion
                eps, inv_sig, ok = np.full(3, np.nan), float("nan"), False
            rows.append((eps[1], eps[0], f_inf + gain * inv_sig, ok))
        a = np.array(rows, dtype=float)
        out = CouplingResult(
            *(torch.as_tensor(a[:, i], dtype=DTYPE) for i in range(3)),
            torch.as_tensor(a[:, 3] > 0),
        )
        return CouplingResult(*(v[0] for v in out)) if single else out

    # ------------------------------------------------------------------ optimum
    def optimum(self, n_starts: int = 8, seed: int = 0) -> tuple[torch.Tensor, float]:
        """True optimum (max loss rate) in the bounds: multi-start L-BFGS-B from zero knobs and
        ``n_starts`` Sobol points; cached.

        Returns:
            ``(x_star, loss_rate_star)`` with ``x_star`` of shape ``K`` (control units).
        """
        if self._optimum is None:
            self._optimum = find_optimum(
                self.loss_rate,
                self.bounds,
                n_starts=n_starts,
                seed=seed,
                x_init=torch.zeros(1, self.dim, dtype=DTYPE),
            )
        x, f = self._optimum
        return x.clone(), f

    def with_seed(self, error_seed: int, **overrides) -> RingCoupling:
        """The same lattice, knobs, calibration and loss-rate map with another error seed."""
        kw = {
            "knob_limit": self.knob_limits,
            "knob_units": self.knob_units,
            "target_ratio": self.target_ratio,
            "loss_rate_map": self.loss_rate_map,
            "name": self.name,
        }
        kw.update(overrides)
        return RingCoupling(
            self._base["ring"], self.knob_names, self.knob_calibration, error_seed=error_seed, **kw
        )


def _per_knob(value, k: int, what: str) -> torch.Tensor:
    t = torch.as_tensor(value, dtype=DTYPE).reshape(-1).clone()
    if t.numel() == 1:
        t = t.expand(k).clone()
    if t.numel() != k:
        raise ValueError(f"{what}: give one value or one per knob ({k}), got {t.numel()}")
    if not (torch.isfinite(t).all() and (t > 0).all()):
        raise ValueError(f"{what} must be positive and finite, got {t.tolist()}")
    return t


@functools.lru_cache(maxsize=16)
def _default_map(base_key, target_ratio: float, calibration: tuple) -> tuple[float, float]:
    base = _BASES[base_key]
    ref = RingCoupling(
        base["ring"],
        list(base_key[1]),
        list(calibration),
        error_seed=LOSS_RATE_ANCHOR[0],
        target_ratio=target_ratio,
        loss_rate_map=(0.0, 1.0),
    )
    return calibrate_loss_rate_map(ref, *LOSS_RATE_ANCHOR[1:])
