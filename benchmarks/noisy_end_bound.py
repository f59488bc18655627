r"""How close to the best reading an ideal estimator ends on a noisy screen.

A run on a machine that does not drift, whose screen reads each of ``m`` observables with
independent Gaussian noise, tuned by an *ideal* estimator: reading :math:`t = 1 \dots N` is taken
at the estimate of the optimum from the :math:`t - 1` readings before it (the first at an estimate
from none: the prior's, error :math:`\sigma_0`), and each reading's estimate error of observable
:math:`j` is the mean of its readings' noise, :math:`e_{t,j} = \frac{1}{t}\sum_{k \le t}
\varepsilon_{k,j}`, :math:`\varepsilon_{k,j} \sim N(0, \sigma_j^2)` (a linear model with one
unknown per observable: the efficient estimate, no estimator does better on average). The true
MAE at reading :math:`t` is :math:`\frac1m\sum_j |e_{t-1,j}|`, the run ends at the estimate from
all :math:`N` readings (final :math:`\frac1m\sum_j |e_{N,j}|`) and the best is the smallest true
MAE of the :math:`N` readings. With forgetting :math:`\lambda < 1` the estimate is the
exponentially weighted mean instead.

The final is the efficient estimate, yet the best is the minimum of :math:`N` correlated draws
that scatter around the optimum by the estimates' errors, so final / best is well above 1 on most
runs: the printout gives its median and the fraction of runs with final <= 1.2x best, and the
final against the reading with the lowest *read* MAE (the "lucky" reading: what a set-back to
the best reading would give; its read MAE adds each reading's noise).

    python benchmarks/noisy_end_bound.py [--readings 100] [--runs 4000] [--seed 0]

Scales (each observable's noise, relative): ``equal`` (1, 1, 1, 1), ``one`` (1, 0, 0, 0: one
noisy observable), ``ares`` (14.8, 0.18, 5.6, 0.40: the residual sd per observable, µm, of
``mu_x, sigma_x, mu_y, sigma_y`` measured on a ``screen-jitter`` tuning run, trial 28).
"""

from __future__ import annotations

import argparse

import numpy as np

#: Relative noise sd of each observable (module docstring).
SCALES: dict[str, tuple[float, ...]] = {
    "equal": (1.0, 1.0, 1.0, 1.0),
    "one": (1.0, 0.0, 0.0, 0.0),
    "ares": (14.8, 0.18, 5.6, 0.40),
}


def ideal_runs(scales, readings: int, runs: int, *, forget: float = 1.0, seed: int = 0):
    r"""``(final, best, lucky)``, each ``runs`` true MAEs (noise units) of ideal runs (module
    docstring): the estimate after ``readings`` readings, the smallest true MAE of the readings,
    the true MAE at the reading with the smallest read MAE. ``forget``: :math:`\lambda`."""
    if readings < 1 or runs < 1 or not 0 < forget <= 1:
        raise ValueError("need readings >= 1, runs >= 1 and 0 < forget <= 1")
    rng = np.random.default_rng(seed)
    s = np.asarray(scales, dtype=float)
    eps = rng.normal(size=(runs, readings, s.size)) * s
    # e[:, t]: the estimate's error from the first t readings (t = 0: the prior's, sigma_0 = s)
    w = forget ** np.arange(readings - 1, -1, -1, dtype=float)
    e = np.empty((runs, readings + 1, s.size))
    e[:, 0] = rng.normal(size=(runs, s.size)) * s
    for t in range(1, readings + 1):
        wt = w[readings - t :]
        e[:, t] = (eps[:, :t] * wt[:, None]).sum(1) / wt.sum()
    true = np.abs(e[:, :-1]).mean(-1)  # runs x readings: reading t at the estimate from t - 1
    read = np.abs(e[:, :-1] + eps).mean(-1)
    final = np.abs(e[:, -1]).mean(-1)
    lucky = true[np.arange(runs), read.argmin(1)]
    return final, true.min(1), lucky


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--readings", type=int, default=100)
    p.add_argument("--runs", type=int, default=4000)
    p.add_argument("--seed", type=int, default=0)
    a = p.parse_args(argv)
    print(f"ideal estimator, {a.readings} readings, {a.runs} runs (ratios of true MAEs)")
    print(f"{'scales':<7} {'forget':>6} {'final/best':>10} {'<=1.2':>6} {'final/lucky':>11} "
          f"{'<=1.2':>6}")  # fmt: skip
    for name, scales in SCALES.items():
        for forget in (1.0, 0.9):
            final, best, lucky = ideal_runs(scales, a.readings, a.runs, forget=forget,
                                            seed=a.seed)  # fmt: skip
            rb, rl = final / best, final / lucky
            print(f"{name:<7} {forget:>6.2f} {np.median(rb):>10.2f} {np.mean(rb <= 1.2):>6.1%} "
                  f"{np.median(rl):>11.2f} {np.mean(rl <= 1.2):>6.1%}")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
