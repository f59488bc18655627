"""Throughput of the fast coupling model vs the pyAT reference path (``pigp bench simulator``).

The numbers depend on what else runs on the machine, so the result records the load average and
the CPU time next to the wall time: ``samples_per_s`` is wall-clock (what a user gets),
``samples_per_cpu_s`` divides by the CPU time this process used (what the code costs, much less
sensitive to other processes on a shared machine).
"""

from __future__ import annotations

import os
import time

import torch


def _best_time(fn, repeats: int) -> tuple[float, float]:
    """Best wall time and best process CPU time of ``repeats`` calls of ``fn`` (seconds)."""
    wall = cpu = float("inf")
    for _ in range(repeats):
        w0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall = min(wall, time.perf_counter() - w0)
        cpu = min(cpu, time.process_time() - c0)
    return wall, cpu


def _load_average() -> list[float] | None:
    try:
        return [round(v, 2) for v in os.getloadavg()]
    except OSError:  # not available on this platform
        return None


def gpu_status() -> tuple[bool, str | None]:
    """``(available, reason)``: whether a CUDA device can run the model, and why not."""
    if not torch.cuda.is_available():
        if torch.version.cuda is None:
            return False, "this torch build has no CUDA support"
        return False, "torch.cuda.is_available() is False (no CUDA device visible)"
    return True, None


def _max_rel_diff(a, b, names) -> dict:
    """Largest relative difference per observable over the rows stable on both paths."""
    ok = (a.stable & b.stable).cpu()
    out = {}
    for k in names:
        x, y = getattr(a, k).detach().cpu()[ok], getattr(b, k).detach().cpu()[ok]
        out[k] = float(((x - y) / y).abs().max()) if len(y) else float("nan")
    return out


def _time_fast(sim, Xd, workers: int, repeats: int) -> dict:
    """Best-of-``repeats`` samples/s of the fast model on ``Xd``'s device (all outputs, and the
    loss rate alone; on the CPU also per CPU-second), after one warm-up evaluation."""
    batch = len(Xd)

    def run(emittances):
        with torch.no_grad():
            sim._equilibrium(Xd, emittances=emittances, workers=workers)
        if Xd.device.type == "cuda":
            torch.cuda.synchronize(Xd.device)

    run(True)  # warm-up (allocations, kernels)
    w_full, c_full = _best_time(lambda: run(True), repeats)
    w_loss, c_loss = _best_time(lambda: run(False), repeats)
    res = {"samples_per_s": batch / w_full, "samples_per_s_loss_rate_only": batch / w_loss}
    if Xd.device.type == "cpu":
        res["samples_per_cpu_s"] = batch / c_full
        res["samples_per_cpu_s_loss_rate_only"] = batch / c_loss
    return res


def _gpu_record(sim, X, devices, fast: dict, gpu_ok: bool, gpu_reason) -> dict:
    """The ``gpu`` entry of :func:`measure_throughput`: availability, the GPU's samples/s and,
    when one was timed, the largest relative difference of its outputs to the CPU's."""
    gpu = next((d for d in devices if d.startswith("cuda")), None)
    record = {
        "available": gpu_ok,
        "reason": gpu_reason,
        "device": torch.cuda.get_device_name(gpu) if gpu else None,
        "samples_per_s": fast[gpu]["samples_per_s"] if gpu else None,
        "samples_per_s_loss_rate_only": fast[gpu]["samples_per_s_loss_rate_only"] if gpu else None,
    }
    if gpu:
        n = min(len(X), 4096)
        record["max_rel_diff_vs_cpu"] = _max_rel_diff(
            sim.evaluate(X[:n].to(gpu)), sim.evaluate(X[:n]), ("eps_y", "eps_x", "loss_rate")
        )
    return record


def measure_throughput(
    sim,
    *,
    batch: int = 100_000,
    n_reference: int = 5,
    repeats: int = 3,
    devices=None,
    workers: int | None = None,
    seed: int = 0,
    progress=None,
) -> dict:
    """Samples per second of ``sim``'s fast model (per device) and of its pyAT reference path.

    Args:
        sim: a :class:`~pigp_torch.machines.ring.spear3.Spear3Coupling`.
        batch: rows per timed evaluation (random settings in the knob box).
        n_reference: settings evaluated by the pyAT reference (for its speed and the agreement).
        repeats: timed repetitions; the best is reported.
        devices: devices to time; default ``cpu`` plus ``cuda`` when available.
        workers: CPU threads evaluating chunks concurrently (default ``torch.get_num_threads()``,
            what :meth:`Spear3Coupling.evaluate` uses).
        seed: seed of the random settings.
        progress: optional callable receiving one-line progress messages.

    Returns:
        A JSON-able dict: ``fast[device]`` with ``samples_per_s`` (full outputs),
        ``samples_per_s_loss_rate_only`` and, on the CPU, the same per CPU-second; ``gpu``
        (``available``, ``reason`` when not, ``samples_per_s`` or ``None``, and the largest
        relative difference GPU vs CPU); the reference path's samples/s and the speed-up;
        ``max_rel_diff`` fast vs reference for εy, εx and the loss rate (rows stable on both)
        and ``stable_agree`` (both paths flag the same rows unstable); the machine's load
        average before and after and its CPU count.
    """
    if batch < 1 or n_reference < 1 or repeats < 1:
        raise ValueError("batch, n_reference and repeats must be >= 1")
    say = progress or (lambda msg: None)
    gpu_ok, gpu_reason = gpu_status()
    if devices is None:
        devices = ["cpu"] + (["cuda"] if gpu_ok else [])
    devices = [str(d) for d in devices]
    workers = workers or torch.get_num_threads()
    g = torch.Generator().manual_seed(seed)
    X = (2 * torch.rand(batch, sim.dim, generator=g, dtype=torch.float64) - 1) * sim.bounds[1]
    out = {
        "batch": batch,
        "knobs": sim.dim,
        "threads": workers,
        "cpu_count": os.cpu_count(),
        "load_average_before": _load_average(),
        "fast": {},
    }
    for device in devices:
        say(f"timing the fast model on {device} ({batch} rows, best of {repeats})")
        out["fast"][device] = _time_fast(sim, X.to(device), workers, repeats)
    out["gpu"] = _gpu_record(sim, X, devices, out["fast"], gpu_ok, gpu_reason)

    say(f"pyAT reference on {n_reference} settings")
    Xr = X[:n_reference]
    t0 = time.perf_counter()
    ref = sim.reference(Xr)
    out["reference_samples_per_s"] = n_reference / (time.perf_counter() - t0)
    fast = sim.evaluate(Xr)
    out["speedup_cpu_vs_reference"] = (
        out["fast"]["cpu"]["samples_per_s"] / out["reference_samples_per_s"]
        if "cpu" in out["fast"]
        else None
    )
    out["max_rel_diff"] = _max_rel_diff(fast, ref, ("eps_y", "eps_x", "loss_rate"))
    out["stable_agree"] = bool((fast.stable == ref.stable).all())
    out["load_average_after"] = _load_average()
    return out
