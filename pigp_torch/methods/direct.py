r"""Direct (model-free) methods: Nelder–Mead and RCDS.

* ``nelder-mead``: adaptive coefficients, ``initial_simplex_size = 0.05`` of each knob's full
  range (= ±0.1 in knob units normalized to :math:`[-1, 1]`), restarts when converged.
* ``nelder-mead-restart``: the same simplex restarted every ``period`` readings (default 50) from
  the re-measured best setting (:class:`~pigp_torch.optimizers.nm_restart.NelderMeadRestart`).
* ``rcds``: ``noise`` the machine's (``ctx.noise``), initial ``step = 0.05`` of the knob range,
  coordinate directions.
"""

from __future__ import annotations

from pigp_torch.methods.registry import RunContext
from pigp_torch.optimizers import RCDS, NelderMead
from pigp_torch.optimizers.nm_restart import DEFAULT_PERIOD, NelderMeadRestart


def build_nelder_mead(
    ctx: RunContext, *, initial_simplex_size: float = 0.05, **options
) -> NelderMead:
    """Nelder–Mead (adaptive coefficients) with the documented initial simplex."""
    return NelderMead(
        ctx.bounds, initial_simplex_size=initial_simplex_size, maximize=ctx.maximize, **options
    )


def build_nelder_mead_restart(
    ctx: RunContext, *, period: int = DEFAULT_PERIOD, initial_simplex_size: float = 0.05, **options
) -> NelderMeadRestart:
    """Nelder–Mead restarted every ``period`` readings from the re-measured best setting, with
    the simplex of ``nelder-mead``."""
    return NelderMeadRestart(
        ctx.bounds,
        period=period,
        initial_simplex_size=initial_simplex_size,
        maximize=ctx.maximize,
        **options,
    )


def build_rcds(
    ctx: RunContext, *, step: float = 0.05, noise: float | None = None, directions=None
) -> RCDS:
    """RCDS with the machine's noise level (``noise=None``: ``ctx.noise``, and RCDS's own
    default when that is unknown)."""
    noise = ctx.noise if noise is None else noise
    kwargs = {} if noise is None else {"noise": noise}
    return RCDS(ctx.bounds, step=step, directions=directions, maximize=ctx.maximize, **kwargs)
