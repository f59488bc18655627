"""Throughput of the fast coupling model vs the pyAT reference path (``pigp bench simulator``)."""

from __future__ import annotations

import time

import torch


def _best_time(fn, repeats: int) -> float:
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def measure_throughput(
    sim,
    *,
    batch: int = 100_000,
    n_reference: int = 5,
    repeats: int = 3,
    devices=("cpu",),
    seed: int = 0,
) -> dict:
    """Samples per second of ``sim.evaluate`` (batched, per device) and ``sim.reference``.

    Returns a JSON-able dict: per device the samples/s with and without the eigen-emittances
    (best of ``repeats``), the reference path's samples/s, their ratio, and the largest relative
    difference of εy and the loss rate between the two paths on the reference points.
    """
    from pigp_torch.simulation.linear_model import equilibrium
    from pigp_torch.simulation.spear3 import CHUNK

    g = torch.Generator().manual_seed(seed)
    X = (2 * torch.rand(batch, sim.dim, generator=g, dtype=torch.float64) - 1) * sim.bounds[1]
    out = {"batch": batch, "knobs": sim.dim, "threads": torch.get_num_threads(), "fast": {}}
    for device in devices:
        Xd = X.to(device)
        model = sim._model(Xd.device)
        order = sim._m["order"].to(Xd.device)

        def run(emittances, Xd=Xd, model=model, order=order):
            with torch.no_grad():
                Xo = Xd[:, order]
                for i in range(0, Xo.shape[0], CHUNK):  # as Spear3Coupling.evaluate does
                    equilibrium(model, Xo[i : i + CHUNK], emittances=emittances)
            if Xd.device.type == "cuda":
                torch.cuda.synchronize()

        run(True)  # warm-up (allocations, kernels)
        out["fast"][str(device)] = {
            "samples_per_s": batch / _best_time(lambda run=run: run(True), repeats),
            "samples_per_s_loss_rate_only": batch / _best_time(lambda run=run: run(False), repeats),
        }
    Xr = X[:n_reference]
    t_ref = _best_time(lambda: sim.reference(Xr), 1)
    ref, fast = sim.reference(Xr), sim.evaluate(Xr)
    out["reference_samples_per_s"] = n_reference / t_ref
    out["speedup_cpu_vs_reference"] = (
        out["fast"]["cpu"]["samples_per_s"] / out["reference_samples_per_s"]
    )
    out["max_rel_diff"] = {
        k: float(((getattr(fast, k) - getattr(ref, k)) / getattr(ref, k)).abs().max())
        for k in ("eps_y", "loss_rate")
    }
    return out
