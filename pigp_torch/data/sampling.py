r"""Simulated coupling data for the surrogate: the sampling design and the dataset it produces.

Design (fractions of ``n``):

* ``global_fraction`` (default 40 %): a scrambled Sobol sequence over the whole knob box. It pins
  down the background level and the heavy-tailed fall-off of the loss rate far from the optimum,
  so the surrogate never extrapolates inside the box.
* the rest: Gaussian draws around the model ring's optimum x* in knob coordinates normalized to
  the half-range, each with its own standard deviation drawn log-uniformly in ``local_scales``
  (default 0.01–0.3), clipped to the box. The physics prior only needs log(f − f∞) and its
  CURVATURE at the optimum, so that is where the surrogate must be most accurate. The peak is
  narrow (along the stiffest direction it spans ~2 % of the half-range), so the small scales
  matter: a fixed σ of 0.05–0.3 left the surrogate's Hessian 6–7 % off, the log-uniform
  mixture covers the curvature, the kernel's correlation lengths and the tails alike.

Everything is deterministic for a given ``seed``. The model ring's optimum is known to the
modeller (it is their own simulation), so using it costs nothing on the real machine.
"""

from __future__ import annotations

import math

import torch
from tqdm.auto import tqdm

from pigp_torch._utils import DTYPE
from pigp_torch._version import __version__
from pigp_torch.data.dataset import Dataset

LOCAL_SCALES = (0.01, 0.3)  # range of the log-uniform cloud widths (normalized knobs)


def sampling_design(
    n: int,
    bounds: torch.Tensor,
    center: torch.Tensor,
    *,
    seed: int = 0,
    global_fraction: float = 0.4,
    local_scales=LOCAL_SCALES,
) -> torch.Tensor:
    r"""``n x d`` knob settings: Sobol over the box plus Gaussian draws around ``center``.

    Args:
        n: number of settings.
        bounds: ``2 x d`` knob bounds.
        center: ``d`` centre of the local draws (the model's optimum).
        seed: seeds the Sobol scrambling and the Gaussian draws.
        global_fraction: share of the Sobol part.
        local_scales: ``(smallest, largest)`` standard deviation of the local draws, as a
            fraction of the half-range; each draw gets its own, log-uniform in this range.
    """
    if n < 1:
        raise ValueError(f"n must be positive, got {n}")
    if not 0.0 <= global_fraction <= 1.0:
        raise ValueError(f"global_fraction must be in [0, 1], got {global_fraction}")
    d = bounds.shape[1]
    lo, hi = bounds[0], bounds[1]
    mid, half = (lo + hi) / 2, (hi - lo) / 2
    n_global = round(n * global_fraction)
    sobol = torch.quasirandom.SobolEngine(d, scramble=True, seed=seed)
    parts = [lo + (hi - lo) * sobol.draw(n_global, dtype=DTYPE)]
    gen = torch.Generator().manual_seed(seed)
    u0 = (center - mid) / half
    lo_s, hi_s = (float(v) for v in local_scales)
    if not 0 < lo_s <= hi_s:
        raise ValueError(f"local_scales must be 0 < smallest <= largest, got {local_scales}")
    n_local = n - n_global
    log_s = torch.rand(n_local, 1, generator=gen, dtype=DTYPE)
    sigma = torch.exp(math.log(lo_s) + (math.log(hi_s) - math.log(lo_s)) * log_s)
    u = u0 + sigma * torch.randn(n_local, d, generator=gen, dtype=DTYPE)
    parts.append(mid + half * u.clamp(-1.0, 1.0))
    return torch.cat(parts)


def generate_dataset(
    sim,
    n: int,
    *,
    seed: int = 0,
    chunk: int = 5000,
    progress: bool = True,
    **design,
) -> Dataset:
    """Sample ``sim`` (a :class:`~pigp_torch.simulation.RingCoupling`) with
    :func:`sampling_design` into a dataset.

    Settings without a stable beam are dropped (their count is in the metadata).
    """
    x_star, f_star = sim.optimum()
    X = sampling_design(n, sim.bounds, x_star, seed=seed, **design)
    cols = {"eps_x": [], "eps_y": [], "loss_rate": [], "stable": []}
    with torch.no_grad():
        for start in tqdm(
            range(0, n, chunk), desc="simulating", unit="chunk", disable=not progress
        ):
            r = sim.evaluate(X[start : start + chunk])
            for k in cols:
                cols[k].append(getattr(r, k))
    out = {k: torch.cat(v) for k, v in cols.items()}
    keep = out.pop("stable")
    metadata = {
        "error_seed": sim.error_seed,
        "optics": getattr(sim, "optics", None),
        "ring": None if getattr(sim, "spec", None) is None else sim.spec.to_dict(),
        "ring_name": sim.name,
        "knob_names": list(sim.knob_names),
        "bounds": sim.bounds.tolist(),
        "units": {
            "x": f"{sim.knob_units} (knob setting; K1s·L = calibration x setting)",
            "loss_rate": "mA/min",
            "eps_x": "m rad",
            "eps_y": "m rad",
        },
        "f_inf": sim.loss_background,
        "error_scale": sim.error_scale,
        "knob_calibration_per_unit": sim.knob_calibration.tolist(),
        "model_optimum": {"x": x_star.tolist(), "loss_rate": f_star},
        "design": {
            "seed": seed,
            "n_requested": n,
            "global_fraction": design.get("global_fraction", 0.4),
            "global": "scrambled Sobol over the box",
            "local_scales": list(design.get("local_scales", LOCAL_SCALES)),
            "local": "Gaussian around the model optimum, per-sample sigma log-uniform in "
            "local_scales (normalized knob units), clipped to the box",
            "n_unstable_dropped": int((~keep).sum()),
        },
        "package_version": __version__,
    }
    return Dataset(x=X[keep], metadata=metadata, **{k: v[keep] for k, v in out.items()})
