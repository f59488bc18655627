"""`pigp bench simulator` numbers: structure, agreement with pyAT, GPU reporting, GPU path."""

import pytest
import torch

from pigp_torch.machines.ring.throughput import gpu_status, measure_throughput
from pigp_torch.simulation import Spear3Coupling

requires_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")


@pytest.fixture(scope="module")
def sim():
    return Spear3Coupling(error_seed=1)


def random_settings(sim, n, seed):
    g = torch.Generator().manual_seed(seed)
    return (2 * torch.rand(n, sim.dim, generator=g, dtype=torch.float64) - 1) * sim.bounds[1]


def test_report_has_speeds_agreement_and_gpu_status(sim):
    """A small run reports positive speeds, pyAT agreement (1e-4, εx 2e-4) and the GPU status."""
    res = measure_throughput(sim, batch=300, n_reference=2, repeats=1, devices=["cpu"])
    cpu = res["fast"]["cpu"]
    for key in (
        "samples_per_s",
        "samples_per_s_loss_rate_only",
        "samples_per_cpu_s",
        "samples_per_cpu_s_loss_rate_only",
    ):
        assert cpu[key] > 0, key
    assert res["batch"] == 300 and res["knobs"] == sim.dim
    assert res["speedup_cpu_vs_reference"] == pytest.approx(
        cpu["samples_per_s"] / res["reference_samples_per_s"]
    )
    assert res["stable_agree"] is True
    for name, tol in (("eps_y", 1e-4), ("loss_rate", 1e-4), ("eps_x", 2e-4)):  # as test_spear3
        assert 0 <= res["max_rel_diff"][name] < tol, name
    available, reason = gpu_status()
    assert res["gpu"]["available"] is available and res["gpu"]["reason"] == reason
    assert res["gpu"]["samples_per_s"] is None  # only "cpu" was timed
    assert len(res["load_average_before"]) == 3


def test_gpu_reason_without_cuda():
    """Without CUDA the status says why, in words; with CUDA there is no reason."""
    available, reason = gpu_status()
    assert available == torch.cuda.is_available()
    assert (reason is None) == available
    if not available:
        assert "CUDA" in reason


def test_bad_arguments_raise(sim):
    """A zero batch is refused with a clear message."""
    with pytest.raises(ValueError, match="batch, n_reference and repeats must be >= 1"):
        measure_throughput(sim, batch=0)


def test_threaded_evaluate_equals_serial(sim):
    """evaluate() on 2 worker threads (its default when torch has 2 threads) = 1 worker."""
    import pigp_torch.machines.ring.ring as spear3

    X = random_settings(sim, 40, seed=1)
    old = spear3.CHUNK
    try:
        spear3.CHUNK = 8  # several chunks
        with torch.no_grad():
            one = sim._equilibrium(X, emittances=True, workers=1)
            two = sim._equilibrium(X, emittances=True, workers=2)
    finally:
        spear3.CHUNK = old
    assert torch.equal(one.stable, two.stable)
    assert torch.equal(one.eps, two.eps) and torch.equal(one.inv_sigma_xy, two.inv_sigma_xy)


def test_loss_rate_skips_emittances_but_equals_evaluate(sim):
    """loss_rate(x) (no eigen-emittances) equals evaluate(x).loss_rate to the last bits."""
    X = random_settings(sim, 9, seed=2)
    assert torch.allclose(sim.loss_rate(X), sim.evaluate(X).loss_rate, rtol=1e-14, atol=0)
    assert sim.loss_rate(X[3]).dim() == 0


@pytest.mark.gpu
@requires_cuda
def test_gpu_path_matches_cpu(sim):
    """On CUDA: values equal the CPU to 1e-10 (eps) / 1e-12 (loss), gradients to 1e-8."""
    X = random_settings(sim, 1000, seed=3)
    cpu, gpu = sim.evaluate(X), sim.evaluate(X.cuda())
    assert torch.equal(cpu.stable, gpu.stable.cpu())
    assert torch.allclose(cpu.eps_y, gpu.eps_y.cpu(), rtol=1e-10, atol=0)
    assert torch.allclose(cpu.eps_x, gpu.eps_x.cpu(), rtol=1e-10, atol=0)
    assert torch.allclose(cpu.loss_rate, gpu.loss_rate.cpu(), rtol=1e-12, atol=0)
    x = X[:4].clone().requires_grad_(True)
    xg = X[:4].cuda().requires_grad_(True)
    (g_cpu,) = torch.autograd.grad(sim.loss_rate(x).sum(), x)
    (g_gpu,) = torch.autograd.grad(sim.loss_rate(xg).sum(), xg)
    assert torch.allclose(g_cpu, g_gpu.cpu(), rtol=1e-8, atol=0)


@pytest.mark.gpu
@requires_cuda
def test_gpu_throughput_is_reported(sim):
    """With a GPU the report has its samples/s and its agreement with the CPU (≤ 1e-10)."""
    res = measure_throughput(sim, batch=20_000, n_reference=1, repeats=1)
    assert res["gpu"]["available"] and res["gpu"]["samples_per_s"] > 0
    assert res["fast"]["cuda"]["samples_per_s_loss_rate_only"] > 0
    assert max(res["gpu"]["max_rel_diff_vs_cpu"].values()) < 1e-10
