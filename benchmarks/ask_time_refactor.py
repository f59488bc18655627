"""Per-ask compute of ``pigp-physics`` and ``pigp-fast``: two checkouts, alternated in one run.

``python benchmarks/ask_time_refactor.py OLD_CHECKOUT NEW_CHECKOUT --seeds 101 102 --budget 31
--repeats 3``: for each method, machine and repeat, one run in each checkout (a subprocess with
``PYTHONPATH`` set to it; old and new alternated so both see the same load) of the spear3-13
setting (kept prior ``docs/data/prior_spear3_seed0_surrogate.json``, 13 knobs, the machine's own
loss-rate map, its noise-free loss rate plus seeded noise), timing every ``ask`` by the thread's
CPU time and by the wall clock; prints the medians (ms) of each checkout and the ratio new / old.
On a shared machine read the CPU-time ratio.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys

import numpy as np

CHILD = r"""
import json, sys, time
import torch
from pigp_torch.bench.protocol import NOISE, benchmark_ring, run_seed
from pigp_torch.methods import METHODS, RunContext
from pigp_torch.prior import PhysicsPrior
from pigp_torch.simulation.spec import as_ring_spec
torch.set_default_dtype(torch.float64)
prior = PhysicsPrior.load("docs/data/prior_spear3_seed0_surrogate.json")
method, seed, budget = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
sim = benchmark_ring(seed, as_ring_spec(None), True)
ctx = RunContext(machine=sim, prior=prior, seed=run_seed(method, seed), noise=NOISE,
                 archive_size=0)
opt = METHODS[method].build(ctx)
gen = torch.Generator().manual_seed(seed)
def read(x):
    with torch.no_grad():
        f = float(sim.loss_rate(x[None])[0])
    return f + NOISE * float(torch.randn((), generator=gen))
x = torch.zeros(sim.dim)
opt.tell(x, read(x))
cpu, wall = [], []
for _ in range(budget - 1):
    t0, w0 = time.thread_time(), time.perf_counter()
    x = opt.ask()
    cpu.append(time.thread_time() - t0)
    wall.append(time.perf_counter() - w0)
    opt.tell(x, read(x))
print(json.dumps({"cpu": cpu, "wall": wall}))
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
    times = {(m, c, k): [] for m in args.methods for c in ("old", "new") for k in ("cpu", "wall")}
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
                    got = json.loads(out.stdout.splitlines()[-1])
                    for kind in ("cpu", "wall"):
                        times[(method, which, kind)] += got[kind]
    for method in args.methods:
        for kind in ("cpu", "wall"):
            old = 1e3 * np.median(times[(method, "old", kind)])
            new = 1e3 * np.median(times[(method, "new", kind)])
            n = len(times[(method, "new", kind)])
            print(f"{method} ({kind} time): median ask old {old:.2f} ms, new {new:.2f} ms "
                  f"({n} asks each); new/old = {new / old:.3f}")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
