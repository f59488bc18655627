r"""The physics prior of a PI-GP: optimum, background, precision matrix, amplitude and noise.

A :class:`PhysicsPrior` is plain data (tensors, floats, strings) and is saved as JSON, so a prior
computed from a model can be inspected, versioned and loaded on the control-room machine without
unpickling anything.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from pigp_torch._utils import DTYPE

#: Tag written into saved files and checked on load.
FORMAT_TAG = "pigp_torch.PhysicsPrior"
FORMAT_VERSION = 1

#: Relative tolerance of the precision symmetry check.
_SYMMETRY_RTOL = 1e-8


def _as_float64(value, name: str) -> Tensor:
    # Python lists/floats straight to float64 (as_tensor would round them through float32)
    t = value if isinstance(value, Tensor) else torch.as_tensor(value, dtype=DTYPE)
    if not (t.is_floating_point() or t.dtype in (torch.int32, torch.int64)):
        raise ValueError(f"{name} must be real-valued, got dtype {t.dtype}")
    t = t.detach().to(dtype=DTYPE, device="cpu").clone()
    if not torch.isfinite(t).all():
        raise ValueError(f"{name} contains NaN or inf")
    return t


def _as_finite_float(value, name: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{name} must be a real number, got {value!r}") from err
    if not math.isfinite(v):
        raise ValueError(f"{name} must be finite, got {v}")
    return v


def _check_spd(M: Tensor, d: int, name: str) -> Tensor:
    """``M`` symmetrized, after checking it is ``d x d``, symmetric and positive definite."""
    if M.shape != (d, d):
        raise ValueError(f"{name} must have shape ({d}, {d}), got {tuple(M.shape)}")
    asym = (M - M.T).abs().max().item()
    if asym > _SYMMETRY_RTOL * M.abs().max().item():
        raise ValueError(f"{name} must be symmetric (max|P - P^T| = {asym:.3g})")
    M = 0.5 * (M + M.T)
    eig_min = torch.linalg.eigvalsh(M).min().item()
    if eig_min <= 0:
        raise ValueError(f"{name} must be positive definite; smallest eigenvalue is {eig_min:.3g}")
    return M


@dataclass(eq=False)
class PhysicsPrior:
    r"""Everything the physics-informed GP takes from the model, in raw knob units.

    The GP built from it (see :func:`pigp_torch.models.physics_informed_gp`) has

    .. math::
        m(\mathbf x) = f_\infty, \qquad
        k(\mathbf x, \mathbf x') = \sigma_f^2 \exp\!\left(-\tfrac12 (\mathbf x - \mathbf x')^\top
        \Sigma (\mathbf x - \mathbf x')\right), \qquad y = f + \varepsilon,\;
        \varepsilon \sim \mathcal N(0, \sigma_n^2),

    with :math:`\Sigma = -H/2` and :math:`H` the Hessian of :math:`\log(f - f_\infty)` at
    :math:`\mathbf x_0`.

    Attributes:
        x0: ``d`` knob setting of the model optimum (knob units, e.g. amps of the skew windings).
        f_x0: objective value :math:`f(\mathbf x_0)` of the model.
        f_inf: background level :math:`f_\infty` (prior mean); must be below ``f_x0``.
        precision: ``d x d`` symmetric positive-definite :math:`\Sigma` (1 / knob²). A
            PRECISION: stiff directions have short correlation lengths.
        amplitude: kernel variance :math:`\sigma_f^2` (objective units squared), > 0.
        noise: measurement noise standard deviation :math:`\sigma_n` (objective units), >= 0.
        knob_names: ``d`` unique knob names.
        bounds: ``2 x d`` lower / upper knob limits.
        gradient: ``d`` gradient of :math:`\log(f - f_\infty)` at ``x0`` (1 / knob); about zero
            at an interior optimum. Defaults to zeros.
        provenance: JSON-serializable information on how the prior was made.
        center_cov: optional ``d x d`` symmetric positive-definite covariance of the machine's
            optimum about the nominal (zero) knob setting, from an ensemble of model rings with
            other error seeds (knob units²). The coupling errors are random with known rms, so
            where the optimum of a machine lies is random too, but in a few directions only
            (90 % of its B-weighted variance in 3 of 13 at SPEAR3). Used by
            :class:`~pigp_torch.optimizers.PhysicsModelBO` as the prior on the fitted centre.
        peak_shape: optional ``d x d`` symmetric positive-definite mean, over the same ensemble,
            of the peak shape :math:`B = \tfrac12 \nabla^2 (f - f_\infty)^{-2}` at each ring's
            optimum (1 / (knob² objective²)). The model ring alone gives
            :math:`B = 2 \Sigma / (f(\mathbf x_0) - f_\infty)^2`; the ensemble mean averages out
            its errors. Used by :class:`~pigp_torch.optimizers.PhysicsModelBO` as the shape of
            the fitted physics form.

    Raises:
        ValueError: on sizes that do not match ``len(knob_names)``, non-finite values, a precision
            that is not symmetric positive definite, ``f_inf >= f_x0``, ``amplitude <= 0``,
            ``noise < 0``, ``bounds`` with lower >= upper, or non-JSON provenance.
    """

    x0: Tensor
    f_x0: float
    f_inf: float
    precision: Tensor
    amplitude: float
    noise: float
    knob_names: list[str]
    bounds: Tensor
    gradient: Tensor | None = None
    provenance: dict[str, Any] = field(default_factory=dict)
    center_cov: Tensor | None = None
    peak_shape: Tensor | None = None

    def __post_init__(self) -> None:
        if isinstance(self.knob_names, str) or not all(isinstance(n, str) for n in self.knob_names):
            raise ValueError("knob_names must be a list of strings")
        self.knob_names = list(self.knob_names)
        d = len(self.knob_names)
        if d == 0:
            raise ValueError("knob_names must name at least one knob")
        if len(set(self.knob_names)) != d:
            raise ValueError(f"knob_names must be unique, got {self.knob_names}")

        self.x0 = _as_float64(self.x0, "x0")
        if self.x0.shape != (d,):
            raise ValueError(f"x0 must have shape ({d},) to match knob_names, got {self.x0.shape}")
        self.bounds = _as_float64(self.bounds, "bounds")
        if self.bounds.shape != (2, d):
            raise ValueError(f"bounds must have shape (2, {d}), got {tuple(self.bounds.shape)}")
        if not (self.bounds[0] < self.bounds[1]).all():
            raise ValueError("bounds: every lower bound must be below its upper bound")
        if self.gradient is None:
            self.gradient = torch.zeros(d, dtype=DTYPE)
        self.gradient = _as_float64(self.gradient, "gradient")
        if self.gradient.shape != (d,):
            raise ValueError(f"gradient must have shape ({d},), got {tuple(self.gradient.shape)}")

        P = _check_spd(_as_float64(self.precision, "precision"), d, "precision")
        self.precision = P
        if self.center_cov is not None:
            C = _as_float64(self.center_cov, "center_cov")
            self.center_cov = _check_spd(C, d, "center_cov")
        if self.peak_shape is not None:
            self.peak_shape = _check_spd(
                _as_float64(self.peak_shape, "peak_shape"), d, "peak_shape"
            )

        self.f_x0 = _as_finite_float(self.f_x0, "f_x0")
        self.f_inf = _as_finite_float(self.f_inf, "f_inf")
        if not self.f_inf < self.f_x0:
            raise ValueError(f"f_inf ({self.f_inf}) must be below f_x0 ({self.f_x0})")
        self.amplitude = _as_finite_float(self.amplitude, "amplitude")
        if self.amplitude <= 0:
            raise ValueError(f"amplitude must be positive, got {self.amplitude}")
        self.noise = _as_finite_float(self.noise, "noise")
        if self.noise < 0:
            raise ValueError(f"noise must be non-negative (a standard deviation), got {self.noise}")

        if not isinstance(self.provenance, dict):
            raise ValueError("provenance must be a dict")
        try:
            self.provenance = json.loads(json.dumps(self.provenance, allow_nan=False))
        except (TypeError, ValueError) as err:
            raise ValueError(f"provenance must be JSON-serializable: {err}") from err

    # ------------------------------------------------------------------ derived quantities
    @property
    def dim(self) -> int:
        """Number of knobs ``d``."""
        return len(self.knob_names)

    @property
    def condition_number(self) -> float:
        r"""Condition number :math:`\lambda_{max}/\lambda_{min}` of ``precision`` (raw units)."""
        eig = torch.linalg.eigvalsh(self.precision)
        return (eig[-1] / eig[0]).item()

    def half_ranges(self) -> Tensor:
        r"""``d`` half-ranges :math:`s = (u - l)/2` of the knob bounds."""
        return 0.5 * (self.bounds[1] - self.bounds[0])

    def normalized_precision(self) -> Tensor:
        r"""Precision in knob coordinates normalized to :math:`[-1, 1]` over ``bounds``.

        With :math:`\mathbf x = \mathbf c + S \mathbf u`, :math:`S = \mathrm{diag}(s)`,
        :math:`s` the half-ranges and :math:`\mathbf c` the centres,
        :math:`\delta_x^\top \Sigma \delta_x = \delta_u^\top (S \Sigma S) \delta_u`:

        .. math:: \Sigma_u = S \Sigma S.

        Returns:
            ``d x d`` tensor (dimensionless).
        """
        s = self.half_ranges()
        return s[:, None] * self.precision * s[None, :]

    def length_scales(self, normalized: bool = False) -> tuple[Tensor, Tensor]:
        r"""Correlation lengths along the eigen-directions of the precision.

        For :math:`\Sigma = V \Lambda V^\top` the kernel along :math:`\mathbf v_i` decays as
        :math:`\exp(-r^2 / (2 \ell_i^2))` with :math:`\ell_i = 1/\sqrt{\lambda_i}`.

        Args:
            normalized: use :meth:`normalized_precision` (lengths in units of the half-range)
                instead of raw knob units.

        Returns:
            ``(lengths, directions)``: ``d`` lengths sorted ascending (stiffest direction
            first) and ``d x d`` unit eigenvectors as columns in the same order.
        """
        P = self.normalized_precision() if normalized else self.precision
        eig, vec = torch.linalg.eigh(P)  # ascending eigenvalues -> descending lengths
        return eig.flip(0).rsqrt(), vec.flip(1)

    def correlation_matrix(self, of: str = "covariance") -> Tensor:
        r"""Correlation matrix of the Gaussian implied by the prior.

        Args:
            of: ``"covariance"`` (default): correlations of :math:`C = \Sigma^{-1}`, the
                covariance of the Gaussian basis function :math:`\exp(-\frac12 \delta^\top
                \Sigma \delta)` — how knobs trade off against each other along the ridge.
                ``"precision"``: the normalized precision (equivalently of :math:`-H`),
                :math:`\Sigma_{ij} / \sqrt{\Sigma_{ii}\Sigma_{jj}}`.

        Returns:
            ``d x d`` symmetric matrix with unit diagonal. Both choices are invariant to a
            rescaling of the knobs.
        """
        if of == "covariance":
            M = torch.cholesky_inverse(torch.linalg.cholesky(self.precision))
        elif of == "precision":
            M = self.precision
        else:
            raise ValueError(f'of must be "covariance" or "precision", got {of!r}')
        s = M.diagonal().rsqrt()
        C = s[:, None] * M * s[None, :]
        return 0.5 * (C + C.T)

    # ------------------------------------------------------------------ persistence
    def to_dict(self) -> dict[str, Any]:
        """Plain-data representation (lists, floats, strings) used by :meth:`save`."""
        return {
            "format": FORMAT_TAG,
            "version": FORMAT_VERSION,
            "knob_names": list(self.knob_names),
            "x0": self.x0.tolist(),
            "f_x0": self.f_x0,
            "f_inf": self.f_inf,
            "precision": self.precision.tolist(),
            "amplitude": self.amplitude,
            "noise": self.noise,
            "bounds": self.bounds.tolist(),
            "gradient": self.gradient.tolist(),
            "provenance": self.provenance,
            **({} if self.center_cov is None else {"center_cov": self.center_cov.tolist()}),
            **({} if self.peak_shape is None else {"peak_shape": self.peak_shape.tolist()}),
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> PhysicsPrior:
        """Inverse of :meth:`to_dict` (validates the format tag and all fields)."""
        if not isinstance(data, dict) or data.get("format") != FORMAT_TAG:
            raise ValueError(f"not a PhysicsPrior record (missing format tag {FORMAT_TAG!r})")
        if data.get("version") != FORMAT_VERSION:
            raise ValueError(f"unsupported PhysicsPrior version {data.get('version')!r}")
        names = ("x0", "f_x0", "f_inf", "precision", "amplitude", "noise", "knob_names", "bounds")
        missing = [n for n in names if n not in data]
        if missing:
            raise ValueError(f"PhysicsPrior record lacks fields {missing}")
        kwargs = {n: data[n] for n in names}
        return cls(
            **kwargs,
            gradient=data.get("gradient"),
            provenance=data.get("provenance", {}),
            center_cov=data.get("center_cov"),
            peak_shape=data.get("peak_shape"),
        )

    def save(self, path: str | Path) -> None:
        """Write the prior as a JSON file (floats written with full round-trip precision)."""
        Path(path).write_text(json.dumps(self.to_dict(), indent=2, allow_nan=False) + "\n")

    @classmethod
    def load(cls, path: str | Path) -> PhysicsPrior:
        """Read a prior written by :meth:`save` (plain JSON, nothing executable)."""
        try:
            data = json.loads(Path(path).read_text())
        except json.JSONDecodeError as err:
            raise ValueError(f"{path} is not valid JSON: {err}") from err
        return cls.from_dict(data)
