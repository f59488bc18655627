"""The machines of a benchmark family, one row each: what they draw and what they give.

Per machine seed: the tune offsets from the user deck (``dnu_x``, ``dnu_y``; pyAT tunes of the
machine's ideal lattice minus the deck's), the global error scale, the skews-off coupling
``eps_ratio0`` = εy/εx, the background ``f_inf``, the loss rate with the skews off ``f0`` and the
machine's optimum ``f_star`` in the knob box (:func:`~pigp_torch.bench.machines
.machine_optimum`, 8 starts), all rates in mA/min; for the wide family also the drawn peak
``f_star_drawn``; with ``--n95`` the oracle bound of ``benchmarks/information_bound.py --csv``
(matched by family and seed). Writes a CSV whose first line is a comment with the command.

    python benchmarks/family_machines.py --family wide --seeds 1-24,101-112 \\
        --n95 runs/n95_wide.csv -o docs/data/family_wide_machines.csv
"""

from __future__ import annotations

import argparse
import os
import sys

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import pandas as pd
import torch

from pigp_torch._utils import DTYPE
from pigp_torch.bench.families import FAMILIES, wide_draw
from pigp_torch.bench.machines import benchmark_ring, machine_optimum
from pigp_torch.commands.compare import seed_list
from pigp_torch.simulation.deck import spear3_ring
from pigp_torch.simulation.spec import SPEAR3


def machine_row(seed: int, family: str, nu0) -> dict:
    """One machine's columns (see the module docstring)."""
    sim = benchmark_ring(seed, SPEAR3, True, family)
    nu = sim.ideal_lattice.get_tune(get_integer=True)[:2] - nu0
    zero = sim.evaluate(torch.zeros(sim.dim, dtype=DTYPE))
    row = {
        "family": family,
        "machine_seed": seed,
        "dnu_x": float(nu[0]),
        "dnu_y": float(nu[1]),
        "error_scale": sim.error_scale,
        "eps_ratio0": float(zero.eps_y / zero.eps_x),
        "f_inf": sim.loss_background,
        "f0": float(zero.loss_rate),
        "f_star": machine_optimum(seed, 8, machine_maps=True, family=family),
    }
    if family == "wide":
        row["f_star_drawn"] = wide_draw(seed).f_star
    return row


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--family", choices=FAMILIES, default="wide")
    p.add_argument("--seeds", default="1-24,101-112", help="machine seeds (default 1-24,101-112)")
    p.add_argument("--n95", default=None, help="information_bound.py CSV to join (n95)")
    p.add_argument("-o", "--out", default=None, help="CSV to write (first line: the command)")
    args = p.parse_args(argv)
    torch.set_default_dtype(DTYPE)
    nu0 = spear3_ring("user").get_tune(get_integer=True)[:2]
    rows = []
    for seed in seed_list(args.seeds):
        rows.append(machine_row(seed, args.family, nu0))
        print(" ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                       for k, v in rows[-1].items()), flush=True)  # fmt: skip
    df = pd.DataFrame(rows)
    if args.n95:
        bound = pd.read_csv(args.n95)
        bound["family"] = bound["family"] if "family" in bound else "project"
        df = df.merge(bound[["family", "machine_seed", "n95"]], how="left")
    with pd.option_context("display.width", 200, "display.max_rows", 200):
        print(df.round(4).to_string(index=False))
        print(df.drop(columns=["family", "machine_seed"]).describe().round(4).to_string())
    if args.out:
        with open(args.out, "w") as fh:
            fh.write("# python benchmarks/family_machines.py " + " ".join(
                sys.argv[1:] if argv is None else argv) + "\n")  # fmt: skip
            df.to_csv(fh, index=False, float_format="%.6g")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
