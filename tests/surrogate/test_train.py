"""Tests of surrogate training: accuracy and Hessian on synthetic landscapes, determinism."""

from __future__ import annotations

import math
import time

import pytest
import torch

from pigp_torch.data.dataset import Dataset
from pigp_torch.surrogate import train_surrogate
from pigp_torch.surrogate.train import split_indices, target_values

QUICK = {"widths": (32, 32), "max_epochs": 150, "batch_size": 128, "progress": False}


@pytest.fixture(scope="module")
def quick_fit(landscape3):
    """Default-target model on 3000 samples of the 3-D landscape (a few seconds)."""
    x = landscape3.sample(3000, seed=3, sigma_frac=(0.02, 0.3))
    y = landscape3(x)
    model, report = train_surrogate(
        (x, y), f_inf=landscape3.f_inf, bounds=landscape3.bounds, **QUICK
    )
    return model, report, x, y


def test_quick_fit_accuracy(quick_fit):
    """Held-out loss rate within 1 % near the optimum and R^2 of the log excess above 0.999."""
    _, report, _, _ = quick_fit
    assert report["near_opt_rel_rmse"] < 0.01
    assert report["val_rel_rmse"] < 0.02
    assert report["val_r2_log_excess"] > 0.999
    assert report["n_train"] == 2700 and report["n_val"] == 300
    assert report["n_clamped"] == 0


def test_quick_fit_hessian_matches_exact(quick_fit, landscape3, hessian_errors):
    """The autograd Hessian of log_excess at the optimum matches -Q to 6 % (Frobenius)."""
    model, _, _, _ = quick_fit
    h = torch.autograd.functional.hessian(model.log_excess, landscape3.mu.clone())
    err = hessian_errors(h, landscape3.hessian_log_excess(), k=2)
    assert err["rel_frob"] < 0.06, err
    assert min(err["cos"]) > 0.99, err
    g = torch.autograd.functional.jacobian(model.log_excess, landscape3.mu.clone())
    # gradient at the true optimum is small on the scale of the curvature (|g| w / (|H| w^2))
    w = 0.015
    assert float(g.norm()) * w < 0.02 * float(torch.linalg.norm(h)) * w**2


def test_inv_sq_target_beats_log_excess_on_hessian(quick_fit, landscape3, hessian_errors):
    """On the same data log_excess flattens the peak: its Hessian error is several times larger."""
    model, _, x, y = quick_fit
    log_model, _ = train_surrogate(
        (x, y), f_inf=landscape3.f_inf, bounds=landscape3.bounds, target="log_excess", **QUICK
    )
    h_true = landscape3.hessian_log_excess()

    def err(m):
        h = torch.autograd.functional.hessian(m.log_excess, landscape3.mu.clone())
        return hessian_errors(h, h_true)["rel_frob"]

    assert err(log_model) > 3 * err(model)


def test_model_returned_in_float64_eval_on_cpu(quick_fit, landscape3):
    """The trained model is float64, in eval mode, and keeps the exact bounds and f_inf."""
    model, report, _, _ = quick_fit
    assert not model.training
    assert all(p.dtype == torch.float64 and p.device.type == "cpu" for p in model.parameters())
    assert torch.equal(model.bounds, landscape3.bounds)
    assert float(model.f_inf) == landscape3.f_inf
    assert report["dtype"] == "float32"


def test_output_normalization_is_training_mean_and_std(quick_fit, landscape3):
    """The stored m, s are the mean/std of the target over the training split (exactly)."""
    model, report, _, y = quick_fit
    i_tr, _ = split_indices(len(y), 0.1, seed=0)
    v = target_values(y, landscape3.f_inf, "inv_sq_excess", report["excess_floor"])[i_tr]
    assert math.isclose(float(model.target_mean), float(v.mean()), rel_tol=1e-12)
    assert math.isclose(float(model.target_std), float(v.std()), rel_tol=1e-12)
    # The fitted normalized output has mean ~0 and std ~1 on the training points (the relative
    # loss weights far, large-w points little, hence the few-% tolerance on the std).
    with torch.no_grad():
        z = model.normalized_output(torch.as_tensor(quick_fit[2])[i_tr])
    assert abs(float(z.mean())) < 0.02 and abs(float(z.std()) - 1) < 0.06


def test_same_seed_same_weights_other_seed_differs(landscape3):
    """Training twice with one seed gives identical weights; another seed gives other weights."""
    x = landscape3.sample(400, seed=5)
    y = landscape3(x)
    kw = {"f_inf": landscape3.f_inf, "bounds": landscape3.bounds, "widths": (8, 8)}
    kw.update(max_epochs=3, batch_size=64, progress=False)
    a, ra = train_surrogate((x, y), seed=7, **kw)
    b, _ = train_surrogate((x, y), seed=7, **kw)
    c, _ = train_surrogate((x, y), seed=8, **kw)
    for (name, p), q in zip(a.state_dict().items(), b.state_dict().values(), strict=True):
        assert torch.equal(p, q), name
    assert not torch.equal(a.net[0].weight, c.net[0].weight)
    assert ra["epochs"] == 3


def test_early_stopping_restores_best_weights(landscape3):
    """With patience 1 training stops in the second half and returns the best-validation weights."""
    x = landscape3.sample(500, seed=12)
    y = landscape3(x)
    model, rep = train_surrogate(
        (x, y), f_inf=landscape3.f_inf, bounds=landscape3.bounds, widths=(8,), max_epochs=40,
        patience=1, batch_size=16, lr=0.05, target="log_excess", progress=False,
    )  # fmt: skip
    assert 20 <= rep["epochs"] < 40 and rep["best_epoch"] < rep["epochs"]  # stopped, not last
    _, i_val = split_indices(500, 0.1, seed=0)
    t = torch.log(y[i_val] - landscape3.f_inf)
    with torch.no_grad():
        mse = torch.mean(((model.log_excess(x[i_val]) - t) / rep["target_std"]) ** 2)
    assert math.isclose(float(mse), rep["best_val_loss"], rel_tol=1e-4)


def test_threads_restored_and_time_limit(landscape3):
    """num_threads is restored after training; time_limit stops the epoch loop early."""
    x = landscape3.sample(300, seed=6)
    y = landscape3(x)
    before = torch.get_num_threads()
    t0 = time.perf_counter()
    _, rep = train_surrogate(
        (x, y), f_inf=0.2, bounds=landscape3.bounds, widths=(8,), max_epochs=10_000,
        batch_size=32, time_limit=0.3, progress=False, num_threads=1,
    )  # fmt: skip
    assert time.perf_counter() - t0 < 5.0
    assert rep["epochs"] < 10_000 and rep["num_threads"] == 1
    assert torch.get_num_threads() == before


@pytest.mark.parametrize("target", ["log_excess", "inv_sq_excess"])
def test_samples_below_background_are_clamped_and_reported(landscape3, target):
    """Loss rates at or below f_inf are clamped to the floor, counted and warned about."""
    x = landscape3.sample(200, seed=7)
    y = landscape3(x)
    y[:3] = landscape3.f_inf - torch.tensor([0.0, 0.01, 0.05], dtype=torch.float64)
    with pytest.warns(UserWarning, match="3 of 200 samples"):
        model, rep = train_surrogate(
            (x, y), f_inf=landscape3.f_inf, bounds=landscape3.bounds, widths=(8,),
            max_epochs=2, progress=False, target=target,
        )  # fmt: skip
    assert rep["n_clamped"] == 3
    excess = y[3:] - landscape3.f_inf
    assert math.isclose(rep["excess_floor"], 1e-3 * float(excess.median()), rel_tol=1e-12)
    assert math.isfinite(float(model.target_mean)) and math.isfinite(float(model.target_std))


def test_accepts_dataset_and_reads_metadata(landscape3):
    """A Dataset supplies f_inf and bounds from its metadata; the report echoes f_inf."""
    x = landscape3.sample(200, seed=8)
    y = landscape3(x)
    z = torch.zeros_like(y)
    meta = {"f_inf": 0.2, "bounds": landscape3.bounds.tolist(), "knob_names": ["a", "b", "c"]}
    ds = Dataset(x=x, loss_rate=y, eps_x=z, eps_y=z, metadata=meta)
    model, rep = train_surrogate(ds, widths=(8,), max_epochs=1, progress=False)
    assert rep["f_inf"] == 0.2 and float(model.f_inf) == 0.2
    assert torch.equal(model.bounds, landscape3.bounds)


def test_bad_inputs_rejected(landscape3):
    """Mismatched shapes, NaN, missing f_inf/bounds and a bad split raise ValueError."""
    x = landscape3.sample(50, seed=9)
    y = landscape3(x)
    b = landscape3.bounds
    kw = {"max_epochs": 1, "progress": False}
    with pytest.raises(ValueError, match="shape"):
        train_surrogate((x, y[:-1]), f_inf=0.2, bounds=b, **kw)
    with pytest.raises(ValueError, match="match bounds"):
        train_surrogate((x[:, :2], y), f_inf=0.2, bounds=b, **kw)
    y_nan = y.clone()
    y_nan[4] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        train_surrogate((x, y_nan), f_inf=0.2, bounds=b, **kw)
    with pytest.raises(ValueError, match="f_inf"):
        train_surrogate((x, y), bounds=b, **kw)
    with pytest.raises(ValueError, match="bounds"):
        train_surrogate((x, y), f_inf=0.2, **kw)
    with pytest.raises(ValueError, match="val_fraction"):
        train_surrogate((x, y), f_inf=0.2, bounds=b, val_fraction=1.0, **kw)
    with pytest.raises(ValueError, match="Hessian"):
        train_surrogate((x, y), f_inf=0.2, bounds=b, activation="relu", **kw)
    with pytest.raises(ValueError, match="unknown target"):
        train_surrogate((x, y), f_inf=0.2, bounds=b, target="exp", **kw)


@pytest.mark.slow
def test_13d_hessian_matches_exact_at_realistic_size(make_landscape, hessian_errors):
    """13 knobs, 100k samples, defaults: Hessian within 5 %, top-3 eigenvectors |cos| > 0.98."""
    land = make_landscape(13, seed=0)
    x = land.sample(100_000, seed=100, sigma_frac=(0.01, 0.3))
    y = land(x)
    model, rep = train_surrogate((x, y), f_inf=land.f_inf, bounds=land.bounds, progress=False)
    h = torch.autograd.functional.hessian(model.log_excess, land.mu.clone())
    err = hessian_errors(h, land.hessian_log_excess(), k=3)
    assert err["rel_frob"] < 0.05, err
    assert min(err["cos"]) > 0.98, err
    assert rep["near_opt_rel_rmse"] < 0.01
    assert rep["val_r2_log_excess"] > 0.999
