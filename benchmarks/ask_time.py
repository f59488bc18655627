r"""Compute per ask of ``pigp-physics``: its defaults against a set of options, in one process.

``python benchmarks/ask_time.py --seeds 1-4 --budget 60``: runs the spear3-13 protocol (the kept
prior ``docs/data/prior_spear3_seed0_surrogate.json``, each machine's own loss-rate map) with
the defaults and with :data:`BEFORE` (the defaults before the information asks and the earlier
evidence check), alternating the two machine by machine so that both see the same load, and
prints per variant the median and 90th percentile of the compute per ask in ms, and the ratio of
the medians. Shared machines are noisy: read the ratio, not the absolute numbers.

``python benchmarks/ask_time.py --seeds 101-102 --budget 100 --driver`` compares instead the two
L-BFGS-B paths with the defaults: scipy's compiled routine driven directly
(:func:`pigp_torch._utils.lbfgsb.minimize_lbfgsb`) against :func:`scipy.optimize.minimize`, and
checks that the two runs of each machine chose the same settings to the bit.

``python benchmarks/ask_time.py --seeds 101-102 --budget 50 --early`` compares the defaults
(schedule ``uui``) with the early-phase information asks ``uuc`` (correlated) and ``uue``
(averaged over the form's posterior), and prints the ratios to the defaults also for the
information asks alone (every third ask, steps 3, 6, ...).

``--busy K`` (with ``--early``) measures twice in one run: first as the machine is, then with
``K`` busy-loop child processes (``K = 2``: both cores of a 2-core machine busy; each child
ends by itself after ``--busy-limit`` seconds and is terminated when the pass ends), and prints
for each pass the medians and the ratios to the defaults of that pass.

    python benchmarks/ask_time.py --early --seeds 101-101 --budget 30 --busy 2
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np

import pigp_torch._utils.lbfgsb as lbfgsb
from pigp_torch.bench.protocol import run_one
from pigp_torch.commands.compare import seed_list
from pigp_torch.methods.registry import METHODS
from pigp_torch.optimizers.physics_bo import relaxed_stages
from pigp_torch.prior import PhysicsPrior

PRIOR = "docs/data/prior_spear3_seed0_surrogate.json"

#: The defaults of ``pigp-physics`` before the information asks and the earlier evidence check.
BEFORE = {
    "info_every": 0,
    "evidence_margin": 3.0,
    "evidence_from": None,
    "relax": list(relaxed_stages(log_beta_std=1.0)),
}

#: The early-phase information asks against the defaults' ``uui``.
EARLY = {"defaults": {}, "uuc": {"schedule": "uuc"}, "uue": {"schedule": "uue"}}


#: A child process that keeps one core busy until its deadline (seconds from its start).
BUSY_LOOP = (
    "import sys, time\nt = time.monotonic() + float(sys.argv[1])\nwhile time.monotonic() < t: pass"
)


def busy_children(count: int, limit_s: float) -> list[subprocess.Popen]:
    """``count`` busy-loop child processes, each ending by itself after ``limit_s`` seconds."""
    return [
        subprocess.Popen([sys.executable, "-c", BUSY_LOOP, str(float(limit_s))])
        for _ in range(int(count))
    ]


def measure(variants: dict, seeds, budget: int, prior, driver: bool = False):
    """Per variant name, the compute of every ask and of the information asks alone (s),
    the variants alternated machine by machine."""
    times: dict[str, list[float]] = {name: [] for name in variants}
    info_times: dict[str, list[float]] = {name: [] for name in variants}
    for seed in seeds:
        settings = []
        for name, (options, direct) in variants.items():
            spec = METHODS["pigp-physics"].with_options(**options)
            lbfgsb._DIRECT_OK = direct and lbfgsb._self_check()
            run = run_one(spec, seed, prior, budget=budget, optimum_starts=0)
            settings.append(run[list(prior.knob_names)].to_numpy())
            asks = run.loc[run["step"] > 0, "ask_time_s"].to_numpy()
            times[name].extend(asks.tolist())
            third = (run["step"] > 0) & (run["step"] % 3 == 0)
            info_times[name].extend(run.loc[third, "ask_time_s"].tolist())
            print(f"machine {seed} {name}: median {1e3 * np.median(asks):.0f} ms per ask",
                  flush=True)  # fmt: skip
        if driver:
            same = np.array_equal(*settings)
            print(f"machine {seed}: the two runs chose the same settings to the bit: {same}")
    lbfgsb._DIRECT_OK = None
    return times, info_times


def report(times: dict, info_times: dict, early: bool) -> None:
    """Print the medians (ms) and the ratios to the first variant."""
    medians = {}
    for name, values in times.items():
        v = 1e3 * np.asarray(values)
        medians[name] = float(np.median(v))
        print(f"{name}: median {medians[name]:.0f} ms, p90 {np.percentile(v, 90):.0f} ms per ask "
              f"({len(v)} asks)")  # fmt: skip
    first, second = list(times)[:2]
    if not early:
        print(f"ratio {first} / {second}: {medians[first] / medians[second]:.2f}")
        return
    for name in list(times)[1:]:
        third = {k: float(np.median(info_times[k])) for k in (first, name)}
        print(f"ratio {name} / {first}: {medians[name] / medians[first]:.2f} over all asks, "
              f"{third[name] / third[first]:.2f} over the information asks "
              f"({1e3 * third[name]:.0f} / {1e3 * third[first]:.0f} ms median)")  # fmt: skip


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", default="1-4", help="machine seeds, e.g. 1-4")
    p.add_argument("--budget", type=int, default=60, help="evaluations per run")
    p.add_argument(
        "--driver", action="store_true", help="direct L-BFGS-B driver against scipy's minimize"
    )
    p.add_argument("--early", action="store_true", help="the early-phase information asks")
    p.add_argument("--busy", type=int, default=0,
                   help="with --early: a second pass, this many busy children")  # fmt: skip
    p.add_argument("--busy-limit", type=float, default=1800.0,
                   help="seconds a busy child lives at most (default 1800)")  # fmt: skip
    args = p.parse_args(argv)
    if args.busy and not args.early:
        raise SystemExit("--busy needs --early")
    prior = PhysicsPrior.load(PRIOR)
    if args.driver:
        variants = {"direct": ({}, True), "scipy": ({}, False)}
    elif args.early:
        variants = {name: (options, True) for name, options in EARLY.items()}
    else:
        variants = {"defaults": ({}, True), "before": (BEFORE, True)}
    seeds = seed_list(args.seeds)
    print("pass 1: the machine as it is")
    report(*measure(variants, seeds, args.budget, prior, args.driver), args.early)
    if args.busy:
        print(f"pass 2: with {args.busy} busy-loop child processes")
        children = busy_children(args.busy, args.busy_limit)
        try:
            report(*measure(variants, seeds, args.budget, prior), early=True)
        finally:
            for child in children:
                child.terminate()
                child.wait(timeout=10)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
