r"""ML-II's wall time per step against torch's thread count, and its scores against the refit
period.

``python benchmarks/ml2_threads.py threads --threads 2 --steps 15``: wall time of ``--steps``
ML-II steps (with its 300-point archive) on tuning machine 101 after ``torch.set_num_threads``
(``0``: torch's default). Run it without ``OMP_NUM_THREADS`` in the environment, on a busy
machine, once per thread count.

``python benchmarks/ml2_threads.py refit --every 5 --budget 40 --seeds 101-106``: ML-II with its
hyperparameters refitted every ``--every`` asks on the tuning machines, printing per machine the
gain fraction after 20 and after ``--budget`` evaluations and their medians and quartiles.
"""

from __future__ import annotations

import argparse
import time


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("what", choices=("threads", "refit"))
    p.add_argument("--threads", type=int, default=0)
    p.add_argument("--steps", type=int, default=15)
    p.add_argument("--every", type=int, default=1)
    p.add_argument("--budget", type=int, default=40)
    p.add_argument("--seeds", default="101-106")
    a = p.parse_args()
    import torch

    if a.what == "threads" and a.threads > 0:
        torch.set_num_threads(a.threads)
    elif a.what == "refit":
        torch.set_num_threads(1)
    from pigp_torch.bench import METHODS, run_one, summarize
    from pigp_torch.bench.protocol import model_prior
    from pigp_torch.commands.compare import seed_list

    prior = model_prior(0, n_starts=2)
    if a.what == "threads":
        t0 = time.perf_counter()
        run_one(METHODS["ml2"], 101, prior, budget=a.steps, optimum_starts=0)
        print(f"{torch.get_num_threads()} thread(s): {a.steps} ML-II steps in "
              f"{time.perf_counter() - t0:.1f} s")  # fmt: skip
        return
    import pandas as pd

    spec = METHODS["ml2"].with_options(refit_every=a.every)
    runs = []
    for seed in seed_list(a.seeds):
        df = run_one(spec, seed, prior, budget=a.budget)
        g = df["gain_fraction"]
        print(f"machine {seed}: gain@20 {g.iloc[:20].max():.3f}, gain@{a.budget} {g.max():.3f}",
              flush=True)  # fmt: skip
        runs.append(df)
    table = summarize(pd.concat(runs, ignore_index=True), at=(20, a.budget))
    print(table.filter(like="gain").to_string(float_format=lambda v: f"{v:.3f}"))


if __name__ == "__main__":
    main()
