"""The dtype and the knob-tensor checks every layer uses (imported as ``pigp_torch._utils.X``)."""

from __future__ import annotations

import contextlib
from datetime import datetime, timezone

import torch

DTYPE = torch.float64


@contextlib.contextmanager
def default_dtype(dtype: torch.dtype = DTYPE):
    """Set torch's default dtype inside the block and restore the caller's afterwards.

    Libraries read the default dtype in places we do not control (e.g. constants inside BoTorch's
    and GPyTorch's numerics), and some change it at import: ``import xopt`` switches the whole
    process to float64. A benchmark run wraps itself in this so that its numbers do not depend
    on what else the process imported, or ran before it.
    """
    saved = torch.get_default_dtype()
    torch.set_default_dtype(dtype)
    try:
        yield
    finally:
        torch.set_default_dtype(saved)


def as_knob_tensor(x, dim: int, *, name: str = "x") -> tuple[torch.Tensor, bool]:
    r"""Validate knob settings and return them as an ``N x dim`` float64 tensor.

    Args:
        x: ``dim`` or ``N x dim`` array-like of knob values.
        dim: number of knobs.
        name: argument name used in error messages.

    Returns:
        ``(X, was_1d)`` where ``X`` is ``N x dim`` and ``was_1d`` says whether a single point
        (shape ``dim``) was given, so callers can squeeze their outputs back.

    Raises:
        ValueError: wrong shape, or NaN/inf entries.
    """
    t = x if isinstance(x, torch.Tensor) else torch.as_tensor(x, dtype=DTYPE)
    if not (t.is_floating_point() or t.dtype in (torch.int32, torch.int64)):
        raise ValueError(f"{name} must be a real-valued tensor, got dtype {t.dtype}")
    if t.dtype != DTYPE:
        t = t.to(DTYPE)
    was_1d = t.dim() == 1
    if was_1d:
        t = t.unsqueeze(0)
    if t.dim() != 2 or t.shape[-1] != dim:
        raise ValueError(
            f"{name} must have shape ({dim},) or (N, {dim}); got {tuple(torch.as_tensor(x).shape)}"
        )
    if not torch.isfinite(t).all():
        bad = (~torch.isfinite(t)).any(dim=-1).nonzero().flatten().tolist()
        raise ValueError(f"{name} contains NaN or inf (rows {bad[:10]})")
    return t, was_1d


def check_bounds(bounds, name: str = "bounds") -> torch.Tensor:
    r"""Validate knob bounds; return them as a ``2 x d`` float64 tensor (row 0 lower, row 1 upper).

    Raises:
        ValueError: wrong shape, non-finite entries, or a lower bound not below its upper bound.
    """
    b = bounds if isinstance(bounds, torch.Tensor) else torch.as_tensor(bounds, dtype=DTYPE)
    b = b.to(DTYPE)
    if b.dim() != 2 or b.shape[0] != 2 or b.shape[1] < 1:
        raise ValueError(f"{name} must have shape (2, d); got {tuple(b.shape)}")
    if not torch.isfinite(b).all():
        raise ValueError(f"{name} must be finite")
    bad = (b[0] >= b[1]).nonzero().flatten().tolist()
    if bad:
        raise ValueError(f"{name}: every lower bound must be below its upper bound (knobs {bad})")
    return b


def max_step_tensor(max_step, bounds: torch.Tensor) -> torch.Tensor | None:
    r"""Per-knob maximum change per ``set`` as a ``d`` tensor (``None``: unlimited).

    A scalar ``s`` is a fraction of each knob's half-range, :math:`s\,(h - \ell)/2` (the same
    normalization as the BayesOpt ``step_limit``: knobs mapped to :math:`[-1, 1]`); a ``d`` tensor
    gives absolute limits in knob units.

    Raises:
        ValueError: non-positive, non-finite, or wrongly shaped limits.
    """
    if max_step is None:
        return None
    bounds = check_bounds(bounds)
    m = torch.as_tensor(max_step, dtype=DTYPE)
    if m.dim() == 0:
        m = m * (bounds[1] - bounds[0]) / 2
    elif m.shape != (bounds.shape[1],):
        raise ValueError(
            f"max_step must be a scalar fraction or a ({bounds.shape[1]},) tensor; "
            f"got shape {tuple(m.shape)}"
        )
    if not torch.isfinite(m).all() or (m <= 0).any():
        raise ValueError("max_step entries must be positive and finite")
    return m


def utc_now() -> str:
    """The current UTC time, ISO 8601 with microseconds."""
    return datetime.now(timezone.utc).isoformat(timespec="microseconds")
