"""Per-ask compute of ``pigp-physics`` and ``pigp-fast``: two checkouts, alternated in one run.

``python benchmarks/ask_time_refactor.py OLD_CHECKOUT NEW_CHECKOUT --seeds 101 102 --budget 31
--repeats 3``: runs the spear3-13 protocol (kept prior ``docs/data/prior_spear3_seed0_surrogate
.json``, 13 knobs) for each method, machine and repeat once in each checkout (a subprocess with
``PYTHONPATH`` set to it, old and new alternated so both see the same load), and prints the
median compute per ask (``ask_time_s`` of the loop's table, ms) of each checkout and the ratio
new / old. Shared machines are noisy: read the ratio, not the absolute numbers.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys

import numpy as np

CHILD = r"""
import json, sys
from pigp_torch.benchmark.protocol import run_one
from pigp_torch.methods import METHODS
from pigp_torch.prior import PhysicsPrior
prior = PhysicsPrior.load("docs/data/prior_spear3_seed0_surrogate.json")
method, seed, budget = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
t = run_one(METHODS[method], seed, prior, budget=budget, optimum_starts=0)
print(json.dumps([float(v) for v in t["ask_time_s"].to_numpy()[1:]]))
"""


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("old")
    p.add_argument("new")
    p.add_argument("--seeds", type=int, nargs="+", default=[101, 102])
    p.add_argument("--budget", type=int, default=31)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--methods", nargs="+", default=["pigp-physics", "pigp-fast"])
    args = p.parse_args(argv)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}
    times = {(m, c): [] for m in args.methods for c in ("old", "new")}
    for r in range(args.repeats):
        for method in args.methods:
            for seed in args.seeds:
                order = ("old", "new") if r % 2 == 0 else ("new", "old")
                for which in order:
                    root = getattr(args, which)
                    out = subprocess.run(
                        [sys.executable, "-c", CHILD, method, str(seed), str(args.budget)],
                        cwd=root, env={**env, "PYTHONPATH": root}, check=True,
                        capture_output=True, text=True,
                    )  # fmt: skip
                    times[(method, which)] += json.loads(out.stdout.splitlines()[-1])
    for method in args.methods:
        old = 1e3 * np.median(times[(method, "old")])
        new = 1e3 * np.median(times[(method, "new")])
        n = len(times[(method, "new")])
        print(f"{method}: median ask old {old:.2f} ms, new {new:.2f} ms ({n} asks each); "
              f"new/old = {new / old:.3f}")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
