r"""A smooth multilayer perceptron that approximates the loss rate as a function of the knobs.

The prior needs the Hessian of :math:`\log(\hat f(x) - f_\infty)` at the optimum, so the network
must be twice differentiable everywhere: only smooth activations are allowed (a ReLU network is
piecewise linear and its Hessian vanishes almost everywhere).
"""

from __future__ import annotations

import math

import torch
from torch import nn

from pigp_torch.surrogate.defaults import ACTIVATION_NAMES, DEFAULT_TARGET, TARGETS

ACTIVATIONS = {"silu": nn.SiLU, "tanh": nn.Tanh, "softplus": nn.Softplus, "gelu": nn.GELU}
assert tuple(sorted(ACTIVATIONS)) == ACTIVATION_NAMES

# Floor keeping log_excess finite where a fitted v leaves its domain (far extrapolation only).
_FLOOR = 1e-12


def _check_bounds(bounds) -> torch.Tensor:
    b = torch.as_tensor(bounds, dtype=torch.float64)
    if b.dim() != 2 or b.shape[0] != 2 or b.shape[1] < 1:
        raise ValueError(f"bounds must have shape (2, d); got {tuple(b.shape)}")
    if not torch.isfinite(b).all():
        raise ValueError("bounds must be finite")
    if (b[0] >= b[1]).any():
        bad = (b[0] >= b[1]).nonzero().flatten().tolist()
        raise ValueError(f"bounds need lower < upper; violated for knob indices {bad}")
    return b


class SurrogateMLP(nn.Module):
    r"""Smooth MLP surrogate :math:`\hat f(x)` of the loss rate with built-in normalizations.

    The knobs are mapped to the unit box with the knob bounds, :math:`u = (x - c) / h`
    (:math:`c`, :math:`h` = box center and half width). The network output :math:`z(u)` is
    de-normalized with the mean :math:`m` and standard deviation :math:`s` of the training
    target, :math:`v = m + s\, z(u)`. What :math:`v` is depends on ``target``; with
    :math:`t = \log(\hat f - f_\infty)` (:meth:`log_excess`, what the prior's Hessian needs):

    ============== ==================================== ======================================
    ``target``     network models :math:`v`             :math:`t(x)`
    ============== ==================================== ======================================
    inv_sq_excess  :math:`(\hat f - f_\infty)^{-2}`      :math:`-\tfrac12 \log \max(v, 10^{-12})`
    log_excess     :math:`\log(\hat f - f_\infty)`      :math:`v`
    inv_excess     :math:`(\hat f - f_\infty)^{-1}`      :math:`-\log \max(v, 10^{-12})`
    raw            :math:`\hat f`                        :math:`\log \max(v - f_\infty, 10^{-12})`
    ============== ==================================== ======================================

    and always :math:`\hat f(x) = f_\infty + e^{t(x)}` (for ``raw``: :math:`\hat f = v`).

    The default ``inv_sq_excess`` is the physics-informed choice: the vertical emittance is
    quadratic in the skew strengths and the loss rate behaves like
    :math:`f_\infty + A/\sqrt{1 + q(x)}`, so :math:`v = (1 + q(x))/A^2` is (nearly) a quadratic
    bowl that a small network fits with an accurate Hessian, whereas :math:`\log(1 + q)` has
    its curvature concentrated at the peak and a fitted network flattens it (the Hessian errors
    of the two targets are compared in docs/results.md).

    Bounds, :math:`f_\infty`, :math:`m` and :math:`s` are float64 buffers: they travel with
    ``state_dict``, ``.to(device)`` and ``.double()``, and are cast to the weights' dtype inside
    the computation.

    Args:
        bounds: ``2 x d`` knob bounds (row 0 lower, row 1 upper), raw knob units.
        f_inf: background loss rate :math:`f_\infty` (the level far from the optimum).
        widths: hidden-layer widths, e.g. ``(64, 64, 64)``; at least one layer.
        activation: ``"silu"`` (default), ``"tanh"``, ``"softplus"`` or ``"gelu"``.
        target: ``"inv_sq_excess"`` (default), ``"log_excess"``, ``"inv_excess"`` or ``"raw"``.
        target_mean: :math:`m`, mean of the training target (set by the trainer).
        target_std: :math:`s`, standard deviation of the training target (positive).

    Raises:
        ValueError: ReLU-type or unknown activation, unknown target, bad bounds or widths,
            non-positive ``target_std``.
    """

    def __init__(
        self,
        bounds,
        f_inf: float,
        *,
        widths=(64, 64, 64),
        activation: str = "silu",
        target: str = DEFAULT_TARGET,
        target_mean: float = 0.0,
        target_std: float = 1.0,
    ) -> None:
        super().__init__()
        act = str(activation).lower()
        if act in ("relu", "leaky_relu", "leakyrelu", "relu6", "prelu", "elu", "selu", "hardtanh"):
            raise ValueError(
                f"activation {activation!r} is not twice continuously differentiable: a ReLU "
                "network is piecewise linear, so its Hessian is zero almost everywhere and the "
                f"physics prior would be meaningless; use one of {sorted(ACTIVATIONS)}"
            )
        if act not in ACTIVATIONS:
            raise ValueError(
                f"unknown activation {activation!r}; choose from {sorted(ACTIVATIONS)}"
            )
        if target not in TARGETS:
            raise ValueError(f"unknown target {target!r}; choose from {TARGETS}")
        widths = tuple(int(w) for w in widths)
        if len(widths) == 0 or any(w < 1 for w in widths):
            raise ValueError(f"widths must be a non-empty sequence of positive ints, got {widths}")
        f_inf = float(f_inf)
        if not math.isfinite(f_inf):
            raise ValueError(f"f_inf must be finite, got {f_inf}")
        if not (math.isfinite(target_std) and target_std > 0):
            raise ValueError(f"target_std must be positive and finite, got {target_std}")
        if not math.isfinite(target_mean):
            raise ValueError(f"target_mean must be finite, got {target_mean}")
        b = _check_bounds(bounds)

        self.dim = int(b.shape[1])
        self.widths = widths
        self.activation = act
        self.target = target

        layers: list[nn.Module] = []
        n_in = self.dim
        for w in widths:
            layers += [nn.Linear(n_in, w), ACTIVATIONS[act]()]
            n_in = w
        layers.append(nn.Linear(n_in, 1))
        self.net = nn.Sequential(*layers)

        # Buffers are created in float64 (exact values); they follow later .to()/.double() calls and
        # are cast to the weights' dtype inside the computation.
        f64 = torch.float64
        self.register_buffer("bounds", b)
        self.register_buffer("f_inf", torch.tensor(f_inf, dtype=f64))
        self.register_buffer("target_mean", torch.tensor(float(target_mean), dtype=f64))
        self.register_buffer("target_std", torch.tensor(float(target_std), dtype=f64))

    @property
    def config(self) -> dict:
        """Architecture (JSON-serializable): what :func:`load_surrogate` needs to rebuild it."""
        return {
            "dim": self.dim,
            "widths": list(self.widths),
            "activation": self.activation,
            "target": self.target,
        }

    # -- internals ---------------------------------------------------------------------------

    def _prepare(self, x) -> tuple[torch.Tensor, bool]:
        """Check ``x`` (``d`` or ``N x d``), cast to the module dtype; returns ``(X, was_1d)``."""
        x = torch.as_tensor(x)
        if not x.is_floating_point():
            x = x.to(torch.float64)
        was_1d = x.dim() == 1
        if was_1d:
            x = x.unsqueeze(0)
        if x.dim() != 2 or x.shape[-1] != self.dim:
            raise ValueError(
                f"x must have shape ({self.dim},) or (N, {self.dim}); got {tuple(x.shape)}"
            )
        if not torch.isfinite(x).all():
            raise ValueError("x contains NaN or inf")
        w = self.net[0].weight
        return x.to(device=w.device, dtype=w.dtype), was_1d

    def normalize_inputs(self, x: torch.Tensor) -> torch.Tensor:
        r"""Map raw knobs ``N x d`` to the unit box: :math:`u = (2x - l - h)/(h - l)`."""
        b = self.bounds.to(x.dtype)
        return (2.0 * x - b[0] - b[1]) / (b[1] - b[0])

    def normalized_output(self, x: torch.Tensor) -> torch.Tensor:
        r"""Raw network output :math:`z` (``N``) for an already validated ``N x d`` input."""
        return self.net(self.normalize_inputs(x)).squeeze(-1)

    def value(self, x: torch.Tensor) -> torch.Tensor:
        r"""De-normalized network output :math:`v = m + s\,z` (``N``) for a validated input."""
        z = self.normalized_output(x)
        return self.target_mean.to(z.dtype) + self.target_std.to(z.dtype) * z

    def _log_excess(self, x: torch.Tensor) -> torch.Tensor:
        v = self.value(x)
        if self.target == "log_excess":
            return v
        if self.target == "inv_sq_excess":
            return -0.5 * torch.log(torch.clamp(v, min=_FLOOR))
        if self.target == "inv_excess":
            return -torch.log(torch.clamp(v, min=_FLOOR))
        return torch.log(torch.clamp(v - self.f_inf.to(v.dtype), min=_FLOOR))

    # -- public ------------------------------------------------------------------------------

    def forward(self, x) -> torch.Tensor:
        r"""Loss rate :math:`\hat f(x) = f_\infty + e^{t(x)}` (``raw``: the network value).

        Args:
            x: ``N x d`` (or ``d``) knob settings in raw units (float32 or float64; cast to the
                module dtype).

        Returns:
            ``N`` loss rates (a scalar for a ``d`` input).
        """
        x, was_1d = self._prepare(x)
        if self.target == "raw":
            y = self.value(x)
        else:
            t = self._log_excess(x)
            y = self.f_inf.to(t.dtype) + torch.exp(t)
        return y.squeeze(0) if was_1d else y

    def log_excess(self, x) -> torch.Tensor:
        r"""Log excess :math:`t(x) = \log(\hat f(x) - f_\infty)`, twice differentiable.

        Args:
            x: ``N x d`` (or ``d``) knob settings in raw units.

        Returns:
            ``N`` values (a scalar for a ``d`` input, so that
            ``torch.autograd.functional.hessian(model.log_excess, x0)`` is ``d x d``).
        """
        x, was_1d = self._prepare(x)
        t = self._log_excess(x)
        return t.squeeze(0) if was_1d else t

    def extra_repr(self) -> str:
        return (
            f"dim={self.dim}, widths={self.widths}, activation={self.activation!r}, "
            f"target={self.target!r}"
        )
