"""ares-physics on machines its model does not contain (tuning trials 0–49 only).

Cases (each a tuning trial changed; stated here, not drawn from the published trials):

* ``right``: the trial as it is;
* ``incoming-out``: the incoming beam's centroid offsets and angles moved outside their prior
  ranges (to the range's edge plus its full width, on the side of the trial's own sign);
* ``misalign-3x``: the eight misalignments multiplied by 3 (up to 3× the range);
* ``k1-10pct``: the machine's quadrupoles 10 % stronger than their set k1 (a calibration error).

    python benchmarks/ares_wrong_model.py --trial-ids 0-4 --cases right k1-10pct --steps 150 \
        [--noise 5e-6] [--method ares-physics]

Prints per run the final and best noise-free MAE (µm), the steps to 40 / 20 µm and the step at
which the prior check fell back to the model-free search (``-``: never).
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import time

import numpy as np
import torch

from pigp_torch.machines.ares_ea.machine import AresMachine
from pigp_torch.machines.ares_ea.methods import ares_objective_for
from pigp_torch.machines.ares_ea.simulation import (
    AresSegment,
    load_lattice,
    load_trials,
    parse_trial_ids,
)
from pigp_torch.methods import METHODS, RunContext

CASES = ("right", "incoming-out", "misalign-3x", "k1-10pct")


class ScaledK1Machine(AresMachine):
    """An ARES machine whose quadrupoles are ``scale`` times stronger than set."""

    def __init__(self, trial, *, scale: float, **kw) -> None:
        super().__init__(trial, **kw)
        self.k1_scale = float(scale)

    def true_observables(self, x) -> torch.Tensor:
        x = torch.as_tensor(x, dtype=torch.float64).clone()
        x[..., [0, 1, 3]] = x[..., [0, 1, 3]] * self.k1_scale
        return super().true_observables(x)


def make_machine(trial, case: str, *, objective: str, noise: float, seed: int, segment):
    kw = dict(objective=objective, noise=noise, seed=seed, segment=segment)
    if case == "right":
        return AresMachine(trial, **kw)
    if case == "k1-10pct":
        return ScaledK1Machine(trial, scale=1.1, **kw)
    if case == "misalign-3x":
        return AresMachine(dataclasses.replace(trial, misalignments=3 * trial.misalignments), **kw)
    if case == "incoming-out":
        rng = load_lattice()["incoming_beam_ranges"]
        lo, hi = torch.tensor(rng["low"]), torch.tensor(rng["high"])
        inc = trial.incoming.clone()
        for i in (1, 2, 3, 4):  # mu_x, mu_xp, mu_y, mu_yp
            sign = 1.0 if inc[i] >= (lo[i] + hi[i]) / 2 else -1.0
            edge = hi[i] if sign > 0 else lo[i]
            inc[i] = edge + sign * (hi[i] - lo[i])
        return AresMachine(dataclasses.replace(trial, incoming=inc), **kw)
    raise ValueError(f"unknown case {case!r}; known: {CASES}")


def run(trial, case, method, *, steps, noise, seed, segment, options=None):
    spec = METHODS[method].with_options(**(options or {}))
    m = make_machine(
        trial, case, objective=ares_objective_for(method), noise=noise, seed=seed, segment=segment
    )
    ctx = RunContext(machine=m, seed=seed, noise=noise or None, archive_size=0, maximize=m.maximize)
    opt = spec.build(ctx)
    maes = []
    for step in range(steps):
        if step:
            m.set(opt.ask())
        x = m.get()
        y = m.read()
        if getattr(opt, "uses_observables", False):
            opt.tell(x, y, observables=m.last_observables)
        else:
            opt.tell(x, y)
        maes.append(float(m.mae(m.true_observables(x))))
    x_best, _ = opt.best()
    final = float(m.mae(m.true_observables(x_best)))
    fell = [n["at_told"] for n in getattr(opt, "notices", []) if n["kind"] == "prior-check"]
    min_p = min((c["p"] for c in getattr(opt, "checks", [])), default=float("nan"))
    return np.array(maes), final, (fell[0] if fell else None), min_p


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--trial-ids", default="0-4")
    p.add_argument("--cases", nargs="+", default=list(CASES))
    p.add_argument("--steps", type=int, default=150)
    p.add_argument("--noise", type=float, default=0.0)
    p.add_argument("--method", default="ares-physics")
    p.add_argument("--opt", action="append", default=[], help="KEY=VALUE method option")
    a = p.parse_args()
    options = {k: ast.literal_eval(v) for k, v in (kv.split("=", 1) for kv in a.opt)}
    ids = parse_trial_ids(a.trial_ids)
    if max(ids) >= 50:
        raise SystemExit("tuning uses trials 0-49 only")
    torch.set_num_threads(1)
    trials, seg = load_trials(), AresSegment()
    for case in a.cases:
        for i in ids:
            t0 = time.perf_counter()
            maes, final, fell, min_p = run(
                trials[i],
                case,
                a.method,
                steps=a.steps,
                noise=a.noise,
                seed=i,
                segment=seg,
                options=options,
            )
            hit40 = np.nonzero(maes <= 40e-6)[0]
            hit20 = np.nonzero(maes <= 20e-6)[0]
            print(
                f"{case:13s} trial {i:2d} {a.method}: final {final * 1e6:8.2f} um  best "
                f"{maes.min() * 1e6:8.2f} um  to40 {hit40[0] if hit40.size else 'inf':>4}  "
                f"to20 {hit20[0] if hit20.size else 'inf':>4}  fallback at "
                f"{fell if fell is not None else '-'}  smallest check p {min_p:.1e}  "
                f"({time.perf_counter() - t0:.0f} s)",
                flush=True,
            )


if __name__ == "__main__":
    main()
