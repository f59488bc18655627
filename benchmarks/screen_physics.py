"""Screen options of ``pigp-physics`` on tuning machines (seeds 101 and up, never 1-24).

Runs each variant (name=option=value,...; a name starting with ``oracle``: the oracle
reference with those options) on the given machine seeds under the spear3-13
protocol (own loss-rate map per machine, noise 0.04, 100 evaluations, start at zero knobs) with
the exact-model prior of model ring 0 and its 40-ring error ensemble, and prints per variant:
machines at 95 % of the gain, median steps-to-95 %, median gain after 20 / 40 / 100
evaluations and the median compute per ask. ``--prior FILE`` screens with a kept prior instead
(e.g. the product's ``docs/data/prior_spear3_seed0_surrogate.json``). ``--family wide`` screens
on the wide family's tuning machines (:mod:`~pigp_torch.benchmark.families`). ``--reported``
allows the benchmark's machines 1-24, to report variants already chosen on tuning machines.

    python benchmarks/screen_physics.py --seeds 101-112 --workers 2 \\
        default "fit_bg=f_inf_std=0.03" "beta1=beta=1.0" 'mi:{"schedule": "mi"}'
"""

from __future__ import annotations

import argparse
import json
import os
import sys

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import pandas as pd

from pigp_torch.bench import METHODS, run_benchmark, summarize
from pigp_torch.bench.families import FAMILIES
from pigp_torch.bench.oracle import ORACLE
from pigp_torch.bench.protocol import ENSEMBLE_SIZE, model_prior
from pigp_torch.optimizers.physics_bo import BROADER_SHAPE, relaxed_stages
from pigp_torch.prior import PhysicsPrior


def base_spec(name: str):
    """The method a variant modifies: ``pigp-physics``, or the oracle reference
    (``pigp-physics-oracle``, each machine's own shape, height and background) for a variant
    whose name starts with ``oracle``."""
    return ORACLE if name.startswith("oracle") else METHODS["pigp-physics"]


def parse_variant(text: str):
    """``name`` or ``name=key=value,key=value`` -> (name, options); values are numbers,
    ``True``/``False`` or words. Keys ``relax.ARG`` set the prior check's later stages to
    ``[BROADER_SHAPE, *relaxed_stages(ARG=value, ...)]`` (e.g. ``relax.f_inf_std=0.3``).
    ``name:{JSON}`` gives the options as a JSON object instead (any value, e.g. a
    ``schedule`` text or a list of ``relax`` stages)."""
    name, colon, rest = text.partition(":")
    if colon and rest.startswith("{") and "=" not in name:
        return name, json.loads(rest)
    name, _, rest = text.partition("=")
    options = {}
    for item in filter(None, rest.split(",")):
        key, value = item.split("=")
        if value in ("True", "False"):
            options[key] = value == "True"
        elif value.isalpha():
            options[key] = value
        else:
            options[key] = float(value) if "." in value else int(value)
    stages = {
        k.removeprefix("relax."): options.pop(k) for k in list(options) if k.startswith("relax.")
    }
    if stages:
        options["relax"] = [BROADER_SHAPE, *relaxed_stages(**stages)]
    return name, options


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("variants", nargs="+", help="name or name=key=value,key=value")
    p.add_argument("--seeds", default="101-112", help="tuning machine seeds a-b (>= 101)")
    p.add_argument("--workers", type=int, default=1)
    p.add_argument("--budget", type=int, default=100)
    p.add_argument(
        "--prior",
        help="prior JSON file (default: the exact-model prior of model "
        "ring 0 with its 40-ring ensemble, computed here)",
    )
    p.add_argument("--family", choices=FAMILIES, default="project",
                   help="machine family (default project)")  # fmt: skip
    p.add_argument("--reported", action="store_true",
                   help="allow the benchmark's seeds 1-24 (to REPORT a chosen variant, never "
                   "to tune on them)")  # fmt: skip
    p.add_argument("-o", "--out", default="runs/screen.csv")
    args = p.parse_args(argv)
    a, b = (int(v) for v in args.seeds.split("-"))
    if a <= 24 and not args.reported:
        raise SystemExit("tune on seeds outside the benchmark's 1-24 (--reported to report)")
    if args.prior:
        prior = PhysicsPrior.load(args.prior)
    else:
        prior = model_prior(0, center_ensemble=ENSEMBLE_SIZE, progress=True)
    specs = []
    for text in args.variants:
        name, options = parse_variant(text)
        specs.append(base_spec(name).with_options(name=name, **options))
    df = run_benchmark(specs, range(a, b + 1), prior=prior, n_workers=args.workers,
                       budgets={"gp": args.budget}, family=args.family)  # fmt: skip
    df.to_csv(args.out, index=False)
    s = summarize(df)
    cols = ["n_reached_95", "steps_to_95_median", "gain_20_median", "gain_40_median",
            "gain_100_median", "ask_time_s_median"]  # fmt: skip
    with pd.option_context("display.width", 200):
        print(s[cols].round(3).to_string())
    return 0


if __name__ == "__main__":
    sys.exit(main())
