"""Where a tracked ARES run could end: several end rules scored on the same run.

Drives ``ares-physics`` (the registry's default, options by ``--options``) on one machine of a
drift or reality-gap family for N readings, as ``benchmarks/drift_bench.py`` does, and then sets
a copy of the machine (the same hidden state and time) to each rule's setting and scores the
true MAE (µm) of one more reading there:

* ``rec``: ``recommend()`` (the default's set-back, what ``drift_bench.py`` scores as final);
* ``ask``: the tracked model's optimum now (``end: now``, the former set-back);
* ``last``: the last reading's setting (stay);
* ``pb10``, ``pb20``: the setting of the reading with the best GP posterior mean among the last
  10 / 20 readings (:func:`~pigp_torch.optimizers.estimate.posterior_best`, setpoints as read);
* a run that tracks: ``b1``, the ask under the filter's fit that forgets nothing (forgetting
  1, relinearized at the weighted batch fit of every reading), and ``bw``, the same fit with
  each observable's own noise (the standard deviation of its residuals over the last 60
  readings at the ``b1`` fit: generalized least squares);
* a run that does not track: ``mo``, the checked model's optimum (its ask, the probe's repeats
  left out), and ``bw``, the ask under the checked fit redone with each observable's own noise
  (the standard deviation of its residuals over every reading).

It prints one JSON line per run: the window median (readings N/2 to N-1), the best and the last
true MAE (µm), each rule's true MAE (µm), the GP's noise sd of the last 10 / 20 readings
(µm; ``rec`` leaves the ask above 4x the stated noise), the noise of the fit at the end (µm:
the stated one or the noise probe's), the observables' own noise of ``bw`` (µm) and the filter's
forgetting (``null`` before tracking).
Tuning trials only (0-49).

    nice -n 10 python benchmarks/ares_end_rules.py screen-jitter 1 [--readings 100] \\
        [--options '{"end": "now"}']
"""

from __future__ import annotations

import argparse
import copy
import json
import sys

import numpy as np
import torch

from pigp_torch._utils import DTYPE, default_dtype
from pigp_torch.machines import KINDS
from pigp_torch.methods import RunContext
from pigp_torch.optimizers.estimate import posterior_best, posterior_fit


def _whitened(model, sd: torch.Tensor):
    """The model in units of each observable's noise ``sd`` (``m``)."""

    def whitened(X: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
        return model(X, theta) / sd

    return whitened


def tracked_ends(opt) -> tuple[dict, torch.Tensor]:
    """``b1`` and ``bw`` of a run that tracks (module docstring) and the noise of ``bw``."""
    from pigp_torch.optimizers.track_filter import UnknownsFilter

    n, P = len(opt.X), opt.center.numel()
    weights = torch.ones(n, dtype=DTYPE)
    for step in opt.steps:  # as the tracker's refit: readings before a step count little
        weights[:step] *= opt.step_forget
    ends = {}
    one = copy.deepcopy(opt)
    f = one.filter
    f.refit(one._rows(n), torch.stack(one.O), weights)
    f.chosen = f.forgets.index(1.0)
    one._refresh_play()
    one.u, one._last_ask = f.u[:P].clone(), None
    ends["b1"] = one.ask()
    with torch.no_grad():
        R = torch.stack(one.O) - f.model(one._rows(n), f.center + f.half_width * f.u)
    sd = R[-min(n, 60) :].std(0).clamp_min(1e-9)
    gls = copy.deepcopy(one)
    g = gls.filter
    w = UnknownsFilter(_whitened(g.model, sd), g.center, g.half_width, g.u.clone(), obs_sd=1.0,
                       prior_sd=g.prior_sd, forgets=(1.0,))  # fmt: skip
    w.refit(gls._rows(n), torch.stack(gls.O) / sd, weights)
    g.U[g.chosen] = w.u
    gls._refresh_play()
    gls.u, gls._last_ask = w.u[:P].clone(), None
    ends["bw"] = gls.ask()
    return ends, sd


def checked_ends(opt) -> tuple[dict, torch.Tensor]:
    """``mo`` and ``bw`` of a run that does not track (module docstring) and the noise of
    ``bw``."""
    from pigp_torch.optimizers._least_squares import fit_unknowns

    ends = {}
    mo = copy.deepcopy(opt)
    mo._probe, mo._last_ask = [], None
    ends["mo"] = mo.ask()
    X, O = torch.stack(opt.X), torch.stack(opt.O)
    with torch.no_grad():
        sd = (O - opt.model(X, opt.theta)).std(0).clamp_min(1e-9)
    u, _ = fit_unknowns(_whitened(opt.model, sd), X, O / sd, opt.center, opt.half_width,
                        obs_sd=1.0, prior_sd=float(opt.settings.prior_sd), u0=opt.u,
                        max_iter=20)  # fmt: skip
    gls = copy.deepcopy(opt)
    gls._probe, gls.u = [], u
    gls._fit_theta = gls.theta.detach().clone()
    gls._best_cache = gls._last_ask = None
    ends["bw"] = gls.ask()
    return ends, sd


def run(family: str, trial: int, readings: int, options: dict, seed: int = 101) -> dict:
    """One run and its end rules (module docstring); true MAE in µm."""
    from pigp_torch.machines.ares_ea.benchmark import check_ares_methods

    (spec,) = check_ares_methods(["ares-physics"])
    spec = spec.with_options(**options) if options else spec
    m = KINDS["ares-ea"].drift_machine(
        family=family, seed=seed, trial=trial, objective="mae", noise=0.0
    )
    ctx = RunContext(machine=m, prior=None, seed=seed + trial, archive_size=0, noise=None,
                     maximize=m.maximize)  # fmt: skip

    def mae(obs) -> float:
        return float((obs - m.target).abs().mean() * 1e6)

    series = []
    with torch.random.fork_rng(devices=[]), default_dtype(DTYPE):
        torch.manual_seed(seed + trial)
        opt = spec.build(ctx)
        for t in range(readings):
            if t > 0:
                m.set(opt.ask())
            x = m.get()
            y = m.read()
            opt.tell(x, y, observables=m.last_observables)
            series.append(mae(m.last_true_observables))
        tracking = bool(getattr(opt, "tracking", False))
        X, Y = torch.stack(opt.X), torch.tensor(opt.Y, dtype=DTYPE)
        ends = {"rec": copy.deepcopy(opt).recommend(), "last": opt.X[-1].clone()}
        ends["ask"] = copy.deepcopy(opt).ask() if tracking else ends["rec"]
        more, sd = (tracked_ends if tracking else checked_ends)(opt)
        ends.update(more)
        noise = {}
        for w in (10, 20):
            k = min(w, len(X))  # all readings in a run shorter than the window
            ends[f"pb{w}"] = X[len(X) - k + posterior_best(X[-k:], Y[-k:], opt.bounds)]
            noise[w] = posterior_fit(X[-k:], Y[-k:], opt.bounds, k=k)[1] * 1e6
        scores = {}
        for name, x in ends.items():
            mm = copy.deepcopy(m)
            mm.set(x)
            mm.read()
            scores[name] = round(mae(mm.last_true_observables), 3)
    s = np.asarray(series)
    return {  # the fit's noise (µm) and the filter's forgetting at the end
        "family": family, "trial": trial, "readings": readings, "tracking": tracking,
        "window_um": round(float(np.median(s[readings // 2 :])), 3),
        "best_um": round(float(s.min()), 3), "last_um": round(float(s[-1]), 3),
        "ends_um": scores, "gp_noise_um": {w: round(v, 3) for w, v in noise.items()},
        "fit_noise_um": round(opt.obs_sd * 1e6, 3),
        "obs_noise_um": [round(float(v) * 1e6, 3) for v in sd],
        "forget": None if getattr(opt, "filter", None) is None else opt.filter.forget,
    }  # fmt: skip


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("family")
    p.add_argument("trial", type=int, help="ARES tuning trial (0-49)")
    p.add_argument("--readings", type=int, default=100)
    p.add_argument("--options", default=None, help="ares-physics options as JSON")
    a = p.parse_args(argv)
    if not 0 <= a.trial < 50:
        print(f"error: trial {a.trial} is not a tuning trial (0-49)", file=sys.stderr)
        return 2
    try:
        options = json.loads(a.options) if a.options else {}
        if a.family not in KINDS["ares-ea"].drift_families():
            raise ValueError(f"unknown family {a.family!r}")
    except ValueError as err:  # json.JSONDecodeError is a ValueError
        print(f"error: {err}", file=sys.stderr)
        return 2
    torch.set_num_threads(1)
    print(json.dumps(run(a.family, a.trial, a.readings, options)), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
