r"""Training of :class:`SurrogateMLP` on simulated data: split, fit, early stopping, metrics."""

from __future__ import annotations

import copy
import math
import time
import warnings
from collections.abc import Callable

import torch

from pigp_torch.surrogate.defaults import TARGETS, TRAIN_DEFAULTS
from pigp_torch.surrogate.mlp import SurrogateMLP, _check_bounds


def _unpack(data, f_inf, bounds) -> tuple[torch.Tensor, torch.Tensor, float, torch.Tensor]:
    """Accept a ``Dataset`` or an ``(X, y)`` pair; fill f_inf/bounds from dataset metadata."""
    if isinstance(data, (tuple, list)):
        if len(data) != 2:
            raise ValueError(f"data must be a Dataset or an (X, y) pair, got {len(data)} items")
        x, y = data
    elif hasattr(data, "x") and hasattr(data, "loss_rate"):
        x, y = data.x, data.loss_rate
        meta = getattr(data, "metadata", {}) or {}
        if f_inf is None and "f_inf" in meta:
            f_inf = float(meta["f_inf"])
        if bounds is None and "bounds" in meta:
            bounds = meta["bounds"]
    else:
        raise ValueError(f"data must be a Dataset or an (X, y) pair, got {type(data).__name__}")
    if f_inf is None:
        raise ValueError("f_inf is required (not given and not in the dataset metadata)")
    if bounds is None:
        raise ValueError("bounds are required (not given and not in the dataset metadata)")
    x = torch.as_tensor(x, dtype=torch.float64).detach().cpu()
    y = torch.as_tensor(y, dtype=torch.float64).detach().cpu()
    b = _check_bounds(bounds)
    if x.dim() != 2 or x.shape[1] != b.shape[1]:
        raise ValueError(
            f"X must have shape (N, {b.shape[1]}) to match bounds; got {tuple(x.shape)}"
        )
    if y.shape != (x.shape[0],):
        raise ValueError(f"y must have shape ({x.shape[0]},) to match X; got {tuple(y.shape)}")
    if not (torch.isfinite(x).all() and torch.isfinite(y).all()):
        raise ValueError("X and y must not contain NaN or inf")
    f_inf = float(f_inf)
    if not math.isfinite(f_inf):
        raise ValueError(f"f_inf must be finite, got {f_inf}")
    return x, y, f_inf, b


def split_indices(n: int, val_fraction: float, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Random train/validation split used by :func:`train_surrogate`: ``(i_train, i_val)``."""
    if not 0.0 < val_fraction < 1.0:
        raise ValueError(f"val_fraction must be in (0, 1), got {val_fraction}")
    n_val = max(1, round(val_fraction * n))
    if n - n_val < 2:
        raise ValueError(
            f"need at least 2 training samples after the split, got {n - n_val} of {n}"
        )
    perm = torch.randperm(n, generator=torch.Generator().manual_seed(int(seed)))
    return perm[n_val:], perm[:n_val]


def target_values(y: torch.Tensor, f_inf: float, target: str, floor: float) -> torch.Tensor:
    r"""The quantity the network models, from loss rates ``y`` (``N``).

    With :math:`e = \max(y - f_\infty, \text{floor})`: ``log_excess`` :math:`\log e`,
    ``inv_sq_excess`` :math:`e^{-2}`, ``inv_excess`` :math:`e^{-1}`, ``raw`` :math:`y`.
    """
    if target not in TARGETS:
        raise ValueError(f"unknown target {target!r}; choose from {TARGETS}")
    e = torch.clamp(y - f_inf, min=floor)
    return {
        "log_excess": torch.log(e),
        "inv_sq_excess": e**-2,
        "inv_excess": 1.0 / e,
        "raw": y,
    }[target]


def _r2(pred: torch.Tensor, true: torch.Tensor) -> float:
    ss_res = torch.sum((pred - true) ** 2)
    ss_tot = torch.sum((true - true.mean()) ** 2)
    return float(1.0 - ss_res / ss_tot) if ss_tot > 0 else float("nan")


def _metrics(model: SurrogateMLP, x, y, t, near_fraction: float) -> dict:
    """Held-out metrics: relative RMSE of y and R^2 of t, on all points and the top fraction."""
    with torch.no_grad():
        y_hat = model(x)
        t_hat = model.log_excess(x)
    rel = (y_hat - y) / y
    n_near = max(1, round(near_fraction * len(y)))
    near = torch.argsort(y, descending=True)[:n_near]
    return {
        "val_rel_rmse": float(rel.pow(2).mean().sqrt()),
        "val_rel_max": float(rel.abs().max()),
        "val_r2_log_excess": _r2(t_hat, t),
        "near_opt_rel_rmse": float(rel[near].pow(2).mean().sqrt()),
        "near_opt_rel_max": float(rel[near].abs().max()),
        "near_opt_r2_log_excess": _r2(t_hat[near], t[near]),
        "near_opt_n": int(n_near),
        "near_opt_min_loss_rate": float(y[near].min()),
    }


def train_surrogate(
    data,
    *,
    f_inf: float | None = None,
    bounds=None,
    widths=TRAIN_DEFAULTS["widths"],
    activation: str = TRAIN_DEFAULTS["activation"],
    target: str = TRAIN_DEFAULTS["target"],
    val_fraction: float = TRAIN_DEFAULTS["val_fraction"],
    batch_size: int = TRAIN_DEFAULTS["batch_size"],
    lr: float = TRAIN_DEFAULTS["lr"],
    lr_min_factor: float = 1e-3,
    weight_decay: float = 0.0,
    max_epochs: int = TRAIN_DEFAULTS["max_epochs"],
    patience: int = TRAIN_DEFAULTS["patience"],
    time_limit: float | None = None,
    excess_floor: float | None = None,
    near_fraction: float = 0.1,
    seed: int = 0,
    device: str | torch.device = "cpu",
    dtype: torch.dtype = torch.float32,
    num_threads: int | None = TRAIN_DEFAULTS["num_threads"],
    progress: bool = True,
    on_epoch: Callable[[dict], None] | None = None,
) -> tuple[SurrogateMLP, dict]:
    r"""Fit a :class:`SurrogateMLP` to loss-rate samples (validation split, early stopping).

    The network output :math:`z` is fitted by AdamW to the normalized target
    :math:`(v - m)/s` (:math:`v` = the target of :class:`SurrogateMLP`, :math:`m, s` its training
    mean and standard deviation) with a cosine learning-rate decay from ``lr`` to
    ``lr * lr_min_factor`` over ``max_epochs``. The loss is the mean squared error in log space:
    plain MSE for ``log_excess``/``raw``, and the squared RELATIVE error
    :math:`((\hat v - v)/v)^2 \approx p^2 (\hat t - t)^2` for ``inv_sq_excess`` (:math:`p = 2`)
    and ``inv_excess`` (:math:`p = 1`). After every epoch the validation loss is computed;
    from the second half of the schedule on, training stops after ``patience`` epochs without
    improvement (or after ``time_limit`` seconds), and the best weights are restored.
    The defaults were tuned (:mod:`~pigp_torch.surrogate.defaults`).

    Args:
        data: a :class:`~pigp_torch.data.dataset.Dataset` or a pair ``(X, y)`` with ``X``: ``N x d``
            knob settings (raw units) and ``y``: ``N`` loss rates.
        f_inf: background loss rate :math:`f_\infty`; default: ``data.metadata["f_inf"]``.
        bounds: ``2 x d`` knob bounds; default: ``data.metadata["bounds"]``.
        widths, activation, target: architecture (see :class:`SurrogateMLP`).
        val_fraction, batch_size: held-out fraction (in ``(0, 1)``); minibatch size.
        weight_decay: AdamW decoupled weight decay.
        lr, lr_min_factor: peak learning rate; final/peak ratio of the cosine decay.
        max_epochs, patience: maximum number of epochs; early-stopping patience (epochs).
        time_limit: optional wall-clock limit in seconds for the epoch loop.
        excess_floor: floor of :math:`y - f_\infty` (default :math:`10^{-3}` times the median
            positive excess); samples below it (e.g. :math:`y \le f_\infty`) are clamped to it,
            left out of :math:`m, s` and counted in the report (a warning says so).
        near_fraction: share of the highest-loss validation points in the report's near-optimum.
        seed: seeds the initialization, the split and the shuffling (same seed, same weights).
        device: ``"cpu"`` or ``"cuda"``; training runs there, the returned model is on CPU.
        dtype: training precision (default float32; float64: slower, same Hessian within noise).
        num_threads: CPU threads of the fit (restored afterwards); ``None``: torch's setting.
        progress: show a tqdm progress bar.
        on_epoch: called after each epoch with ``{"epoch", "max_epochs", "train_loss",
            "val_loss", "best_val_loss", "best_epoch", "elapsed_s"}`` (e.g. progress lines).

    Returns:
        ``(model, report)``: the model in ``float64`` eval mode on CPU, and a dict with the
        held-out metrics (``val_rel_rmse``: relative RMSE of the loss rate, ``val_r2_log_excess``:
        :math:`R^2` of :math:`\log(y - f_\infty)`, the same with prefix ``near_opt_`` on the
        near-optimum subset), ``train_time_s``, ``epochs``, ``best_epoch``, ``n_train``,
        ``n_val``, ``n_clamped``, ``excess_floor`` and the settings used.

    Raises:
        ValueError: bad shapes, NaN, missing ``f_inf``/``bounds``, bad fractions or sizes.
    """
    kwargs = dict(locals())
    if num_threads is None:
        return _train(**kwargs)
    previous = torch.get_num_threads()
    torch.set_num_threads(int(num_threads))
    try:
        return _train(**kwargs)
    finally:
        torch.set_num_threads(previous)


def _train(
    data,
    *,
    f_inf,
    bounds,
    widths,
    activation,
    target,
    val_fraction,
    batch_size,
    lr,
    lr_min_factor,
    weight_decay,
    max_epochs,
    patience,
    time_limit,
    excess_floor,
    near_fraction,
    seed,
    device,
    dtype,
    num_threads,
    progress,
    on_epoch,
) -> tuple[SurrogateMLP, dict]:
    x, y, f_inf, b = _unpack(data, f_inf, bounds)
    if target not in TARGETS:
        raise ValueError(f"unknown target {target!r}; choose from {TARGETS}")
    if batch_size < 1 or max_epochs < 1 or patience < 1:
        raise ValueError("batch_size, max_epochs and patience must be positive")
    i_tr, i_val = split_indices(x.shape[0], val_fraction, seed)
    t, v, c, (mean, std), excess_floor, n_clamped = _targets(y, f_inf, target, excess_floor, i_tr)

    torch.manual_seed(int(seed))
    model = SurrogateMLP(
        b, f_inf, widths=widths, activation=activation, target=target, target_mean=mean,
        target_std=std,
    )  # fmt: skip
    dev = torch.device(device)
    model = model.to(device=dev, dtype=dtype)

    def put(idx):
        z = ((v[idx] - mean) / std).to(device=dev, dtype=dtype)
        return x[idx].to(device=dev, dtype=dtype), z, c[idx].to(device=dev, dtype=dtype)

    schedule = dict(
        batch_size=batch_size, lr=lr, lr_min_factor=lr_min_factor, weight_decay=weight_decay,
        max_epochs=max_epochs, patience=patience, time_limit=time_limit,
    )  # fmt: skip
    fit = _fit(
        model, put(i_tr), put(i_val), seed=seed, progress=progress, on_epoch=on_epoch, **schedule
    )
    model.load_state_dict(fit.pop("best_state"))
    model = model.to(device="cpu", dtype=torch.float64).eval()
    with torch.no_grad():  # exact float64 values (training in float32 rounded the buffers)
        model.bounds.copy_(b)
        model.f_inf.fill_(f_inf)
        model.target_mean.fill_(mean)
        model.target_std.fill_(std)
    report = {"n_train": len(i_tr), "n_val": len(i_val), **fit, "n_clamped": n_clamped}
    report.update({
        "excess_floor": float(excess_floor), "f_inf": f_inf, "target": target,
        "target_mean": mean, "target_std": std, "widths": list(model.widths),
        "activation": model.activation, "batch_size": int(batch_size), "lr": float(lr),
        "weight_decay": float(weight_decay), "max_epochs": int(max_epochs), "seed": int(seed),
        "device": str(dev), "dtype": str(dtype).replace("torch.", ""),
        "num_threads": torch.get_num_threads(),
    })  # fmt: skip
    report.update(_metrics(model, x[i_val], y[i_val], t[i_val], near_fraction))
    return model, report


def _targets(y: torch.Tensor, f_inf: float, target: str, excess_floor, i_tr: torch.Tensor):
    r"""What the network is fitted to, from the loss rates ``y`` (``N``): the log excess
    :math:`t = \log \max(y - f_\infty, \text{floor})`, the target :math:`v`
    (:func:`target_values`), the per-sample loss weights :math:`c` (the relative error of
    :math:`v`, :math:`c \propto (s / v)^2`, for the inverse-power targets; else 1) and the
    normalization :math:`(m, s)` of :math:`v` over the training points ``i_tr`` that were not
    clamped; returns ``(t, v, c, (m, s), floor, n_clamped)``. Default floor: :math:`10^{-3}`
    times the median positive excess; a warning counts the clamped samples."""
    n = y.shape[0]
    excess = y - f_inf
    if excess_floor is None:
        pos = excess[excess > 0]
        excess_floor = 1e-3 * float(pos.median()) if len(pos) else 1e-12
    if not excess_floor > 0:
        raise ValueError(f"excess_floor must be positive, got {excess_floor}")
    clamped = excess < excess_floor
    n_clamped = int(clamped.sum())
    if n_clamped:
        warnings.warn(
            f"{n_clamped} of {n} samples have loss rate - f_inf below {excess_floor:.3g}; "
            "clamped to that floor before the transform",
            stacklevel=4,
        )
    t = torch.log(torch.clamp(excess, min=excess_floor))
    v = target_values(y, f_inf, target, excess_floor)
    v_stat = v[i_tr][~clamped[i_tr]]
    if len(v_stat) < 2:
        v_stat = v[i_tr]
    mean, std = float(v_stat.mean()), float(v_stat.std())
    if not (std > 0 and math.isfinite(std)):
        std = 1.0
    if target in ("inv_sq_excess", "inv_excess"):
        c = (std / v) ** 2
        c = c / c[i_tr].mean()
    else:
        c = torch.ones(n, dtype=torch.float64)
    return t, v, c, (mean, std), excess_floor, n_clamped


def _weighted_mse(z_hat, z, w):
    return torch.mean(w * (z_hat - z) ** 2)


def _fit(
    model: SurrogateMLP,
    train,
    val,
    *,
    seed,
    progress,
    on_epoch,
    batch_size,
    lr,
    lr_min_factor,
    weight_decay,
    max_epochs,
    patience,
    time_limit,
) -> dict:
    """AdamW with the cosine decay on the ``(x, z, c)`` tensors ``train``, the validation loss
    on ``val`` after each epoch, early stopping (:func:`train_surrogate`). Returns the epochs,
    best epoch, time, best validation and final training loss, and ``best_state`` (weights)."""
    (x_tr, z_tr, c_tr), (x_va, z_va, c_va) = train, val
    n_train, dev, dtype = x_tr.shape[0], x_tr.device, x_tr.dtype
    opt = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=weight_decay)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(
        opt, T_max=max_epochs, eta_min=lr * lr_min_factor
    )
    gen = torch.Generator().manual_seed(int(seed) + 1)
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=max_epochs, desc="train surrogate", unit="epoch", leave=False)
    best_val, best_state, best_epoch, epoch = float("inf"), None, 0, 0
    train_loss = float("nan")
    t0 = time.perf_counter()
    for epoch in range(1, max_epochs + 1):
        model.train()
        order = torch.randperm(n_train, generator=gen).to(dev)
        total = torch.zeros((), device=dev, dtype=dtype)
        for start in range(0, n_train, batch_size):
            idx = order[start : start + batch_size]
            opt.zero_grad(set_to_none=True)
            loss = _weighted_mse(model.normalized_output(x_tr[idx]), z_tr[idx], c_tr[idx])
            loss.backward()
            opt.step()
            total += loss.detach() * len(idx)
        sched.step()
        model.eval()
        with torch.no_grad():
            val = float(_weighted_mse(model.normalized_output(x_va), z_va, c_va))
        train_loss = float(total) / n_train
        if not math.isfinite(val):
            raise RuntimeError(f"training diverged at epoch {epoch} (validation loss {val})")
        if val < best_val:
            best_val, best_epoch = val, epoch
            best_state = copy.deepcopy(model.state_dict())
        if bar is not None:
            bar.update(1)
            bar.set_postfix(train=f"{train_loss:.2e}", val=f"{val:.2e}", best=f"{best_val:.2e}")
        if on_epoch is not None:
            on_epoch({"epoch": epoch, "max_epochs": max_epochs, "train_loss": train_loss,
                      "val_loss": val, "best_val_loss": best_val, "best_epoch": best_epoch,
                      "elapsed_s": time.perf_counter() - t0})  # fmt: skip
        # No early stop in the first half of the cosine schedule: at the high learning rate the
        # validation loss is noisy and a plateau there is not convergence.
        if epoch >= max_epochs // 2 and epoch - best_epoch >= patience:
            break
        if time_limit is not None and time.perf_counter() - t0 > time_limit:
            break
    train_time = time.perf_counter() - t0
    if bar is not None:
        bar.close()
    return {
        "epochs": epoch, "best_epoch": best_epoch, "train_time_s": train_time,
        "best_val_loss": best_val, "final_train_loss": train_loss, "best_state": best_state,
    }  # fmt: skip
