"""Run benchmark methods on the spear3-13 machines with a prior read from a file.

`pigp compare` builds its prior at every call (the surrogate is retrained, minutes, and float32
training is not bit-reproducible across processes); this script reads one prior file (built
once, e.g. by ``pigp build-prior --center-ensemble 40`` or
``benchmark.model_prior(...).save(path)``) so that several invocations, e.g. one per group of
methods, run against the SAME prior and can be joined into one table. Same protocol as
``pigp compare`` (machines with their own loss-rate maps, noise 0.04 mA/min, start at zero
knobs, budgets 100 / 300 evaluations).

    python benchmarks/run_table.py --prior runs/prior_surrogate.json --seeds 1-24 \\
        --methods xopt-ucb xopt-ucb-travel --workers 1 -o runs/table_xopt.csv

``pigp-physics-oracle`` (:data:`pigp_torch.bench.oracle.ORACLE`, each machine's own shape,
background and peak) is accepted as a reference; ``--suffix=-exact`` labels a run with another
prior file. ``--family wide`` runs the wide family of machines
(:mod:`~pigp_torch.bench.families`; the table's ``family`` column says which).
"""

from __future__ import annotations

import argparse
import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

from pigp_torch.bench import METHODS, run_benchmark, summarize
from pigp_torch.bench.families import FAMILIES
from pigp_torch.bench.oracle import ORACLE
from pigp_torch.commands.compare import seed_list
from pigp_torch.prior import PhysicsPrior


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--prior", required=True, help="prior JSON file (from a model ring)")
    p.add_argument("--methods", nargs="+", required=True, help="method names")
    p.add_argument("--seeds", default="1-24", help="machine error seeds (default 1-24)")
    p.add_argument("--workers", type=int, default=1, help="worker processes (default 1)")
    p.add_argument("--suffix", default="", help="appended to the method names (e.g. -exact)")
    p.add_argument("--family", choices=FAMILIES, default="project",
                   help="machine family (default project)")  # fmt: skip
    p.add_argument("-o", "--out", required=True, help="CSV of every evaluation")
    args = p.parse_args(argv)
    prior = PhysicsPrior.load(args.prior)
    known = {**METHODS, ORACLE.name: ORACLE}  # the oracle is a reference, not a product method
    specs = [known[m].with_options(name=m + args.suffix) for m in args.methods]
    df = run_benchmark(specs, seed_list(args.seeds), prior=prior, n_workers=args.workers,
                       family=args.family)  # fmt: skip
    df.to_csv(args.out, index=False)
    cols = ["n_reached_95", "steps_to_95_median", "gain_20_median", "gain_40_median",
            "gain_100_median", "ask_time_s_median"]  # fmt: skip
    print(summarize(df)[cols].round(3).to_string())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
