r"""The acting fields of magnets with play (backlash), from the setpoints an optimizer was told.

A magnet with play of half width :math:`w \ge 0` acts with the field :math:`y_t = x_t + h_t`
(knob units) where :math:`x_t` is the setpoint of reading :math:`t` and the offset follows the
setpoint path,

.. math:: h_t = \operatorname{clip}(h_{t-1} - (x_t - x_{t-1}), -w, w),

the play operator :math:`y_t = \min(x_t + w, \max(x_t - w, y_{t-1}))`: a move smaller than the
play leaves the field where it was (:math:`y_t = y_{t-1}`), a longer one drags it behind the
setpoint, :math:`h_t = -\operatorname{sign}(x_t - x_{t-1})\,w` (after a move over :math:`2w`
whatever the state before). With :math:`w = 0` the field is the setpoint.

The state before the first reading, :math:`h_{-1} = g \in [-w, w]`, is the history before the
run (unknown: a fit starts it at 0, the middle of the play); the first move past the play
forgets it. For a fit of :math:`w` and :math:`g` the offsets are linear in them along a fixed path
of clip events: :math:`h_t(w, g) = a_t + D_t w + E_t g` with :math:`D_t = \partial h_t / \partial
w` and :math:`E_t = \partial h_t / \partial g` (one number each per magnet), carried along the
path: where the clip acts, :math:`D_t = \pm 1` (the offset sits at :math:`\pm w`) and
:math:`E_t = 0`; where it does not, :math:`D_t = D_{t-1}`, :math:`E_t = E_{t-1}`
(:math:`D = 0`, :math:`E = 1` before the first clip).

The inverse: the setpoint that makes the field :math:`y^*` from the state :math:`(x, h)` is
:math:`y^* + w` when :math:`y^* > x + h` (the field is dragged up from below), :math:`y^* - w` when
:math:`y^* < x + h`, and :math:`x` (no move) when :math:`y^* = x + h` (:func:`setpoint_for`).
"""

from __future__ import annotations

import torch

from pigp_torch._utils import DTYPE

__all__ = ["play_path", "setpoint_for"]


def play_path(X, width, start=None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    r"""The offsets of the acting fields along a setpoint path (module docstring).

    Args:
        X: ``T x d`` setpoints of the readings, in order (knob units).
        width: ``d`` play half widths (knob units; negative values count as 0).
        start: ``d`` offsets :math:`g` before the first reading (knob units, clipped to the
            play; default 0).

    Returns:
        ``(H, D, E)``: ``T x d`` offsets :math:`h_t = y_t - x_t` and the ``T x d`` derivatives
        :math:`\partial h_t / \partial w` and :math:`\partial h_t / \partial g` (so that
        :math:`h_t(w', g') = h_t + D_t (w' - w) + E_t (g' - g)` while the same clips act).
    """
    X = torch.as_tensor(X, dtype=DTYPE)
    w = torch.as_tensor(width, dtype=DTYPE).reshape(-1).clamp_min(0.0)
    h = torch.zeros_like(w) if start is None else torch.as_tensor(start, dtype=DTYPE).clone()
    dw, dg = torch.zeros_like(w), torch.ones_like(w)
    H, D, E = [], [], []
    for t in range(X.shape[0]):
        if t:
            h = h - (X[t] - X[t - 1])
        hi, lo = h > w, h < -w
        dw = torch.where(hi, 1.0, torch.where(lo, -1.0, dw)).to(DTYPE)
        dg = torch.where(hi | lo, 0.0, dg).to(DTYPE)
        h = torch.minimum(torch.maximum(h, -w), w)
        H.append(h)
        D.append(dw)
        E.append(dg)
    return torch.stack(H), torch.stack(D), torch.stack(E)


def setpoint_for(y_target, x, h, width) -> torch.Tensor:
    r"""``d`` setpoints that make the acting fields ``y_target`` (``d``) from the state: setpoints
    ``x`` and offsets ``h`` of the last reading, play half widths ``width`` (module docstring;
    the knob units throughout)."""
    y_target = torch.as_tensor(y_target, dtype=DTYPE)
    w = torch.as_tensor(width, dtype=DTYPE).clamp_min(0.0)
    move = y_target - (x + h)
    return torch.where(move > 0, y_target + w, torch.where(move < 0, y_target - w, x))
