"""Where a tracked run ends (``recommend()`` while tracking): the tracked model's optimum now
on readings as precise as stated (the former set-back, to the bit), the recent reading with the
best GP posterior mean on readings that scatter more than stated."""

from __future__ import annotations

import copy

import torch

from .test_model_check import _run
from .test_tracking import TARGET, _drift_run, _toy, _toy_optimizer

D = torch.float64


def test_readings_as_precise_as_stated_end_at_the_tracked_optimum_now_to_the_bit():
    """The drifting toy read at its stated noise: recommend() is the ask of the same state,
    as with ``end="now"`` (the former set-back)."""
    for end in ("recent", "now"):
        opt = _toy_optimizer(end=end)
        _drift_run(opt, n=40, offset=lambda t: -0.2 + 0.002 * t)
        assert opt.tracking
        expected = copy.deepcopy(opt).ask()
        assert torch.equal(opt.recommend(), expected)


def _noisy_run(seed: int, end: str, sd: float = 0.03, n: int = 60, noise_probe: int = 0):
    """A static toy machine with a term the model lacks (tracking starts), read with noise
    ``sd`` where 0.001 is stated; returns the optimizer and the true MAE at the end setting.
    Without the noise probe by default (the end rules below are for a noise the probe did not
    see: the tracker then believes the stated one)."""
    truth = torch.tensor([1.3, -0.2, 0.8], dtype=D)

    def true(x):
        return _toy(x[None], truth)[0] + torch.stack([0.5 * x[1] ** 2, 0.4 * x[0] ** 2])

    opt = _toy_optimizer(end=end, noise_probe=noise_probe)
    _run(opt, true, sd, n, seed)
    return opt, float((true(opt.recommend()) - TARGET).abs().mean())


def test_readings_that_scatter_more_than_stated_end_at_a_recent_reading():
    """Noise 30x the stated: the end setting is one of the last 10 readings' settings (the GP's
    choice; the toy takes up no play), not the tracked optimum now; with ``end="now"`` it is
    the ask."""
    opt, _ = _noisy_run(0, "recent")
    assert opt.tracking and opt._used_play is None
    x = opt.recommend()
    assert any(torch.equal(x, s) for s in opt.X[-10:])
    assert not torch.equal(x, copy.deepcopy(opt).ask())
    now, _ = _noisy_run(0, "now")
    assert torch.equal(now.recommend(), copy.deepcopy(now).ask())


def test_on_readings_thirty_times_noisier_than_stated_the_end_is_nearer_the_optimum():
    """Six seeds of the noisy toy: the true MAE at the end setting averages under 0.6x that of
    the tracked optimum now (the former end: the model chases single readings) and is the
    smaller in at least 4 of 6."""
    ours, former = [], []
    for seed in range(6):
        opt, mae = _noisy_run(seed, "recent")
        now, mae_now = _noisy_run(seed, "now")
        assert torch.equal(torch.stack(opt.X), torch.stack(now.X))  # the same readings
        ours.append(mae)
        former.append(mae_now)
    assert sum(ours) < 0.6 * sum(former), (ours, former)
    assert sum(a < b for a, b in zip(ours, former, strict=True)) >= 4, (ours, former)


def test_the_noise_probe_learns_the_scatter_and_the_run_ends_nearer_the_optimum():
    """The same six noisy runs with the default noise probe (two repeat readings at the first
    failed check): the noise of the fit is the scatter (within 0.5x-2x of 0.03), and the true
    MAE at the end setting is smaller in total than without the probe, whose end rule chooses
    among the recent readings."""
    probed, blind = [], []
    for seed in range(6):
        opt, mae = _noisy_run(seed, "recent", noise_probe=2)
        assert 0.015 < opt.obs_sd < 0.06, opt.obs_sd
        probed.append(mae)
        blind.append(_noisy_run(seed, "recent")[1])
    assert sum(probed) < sum(blind), (probed, blind)
