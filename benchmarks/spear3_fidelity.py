"""The real-deck SPEAR3 model rings: error scale, optimum and kernel fidelity over many seeds.

For each error seed: the calibrated global error scale (x the nominal rms), the optimum inside
±30 A (largest |knob| in A, εy/εx there, loss rate), and the fidelity of Σ = −H/2 of
log(f − f∞) at the optimum to the authors' SPEAR3 precision (top-3 subspace cosines, diagonal and
off-diagonal correlations, condition number). Prints one row per seed and the distribution.

    python benchmarks/spear3_fidelity.py --seeds 1001-1040
    python benchmarks/spear3_fidelity.py --seeds 0-3 --surrogate   # also the paper's chain

With ``--surrogate`` each ring's simulated data (100k samples) trains a 3-network surrogate, and
the same measures are printed for Σ = −H/2 of the surrogate at the ring's optimum, with its
held-out error and the Frobenius distance to the exact Σ.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np
import torch

from pigp_torch.simulation import Spear3Coupling

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "simulation"))
from test_fidelity import authors_precision, fidelity, model_precision


def surrogate_row(sim, x, P, names) -> None:
    """Train the paper's chain on ``sim`` and print the fidelity of its Hessian at ``x``."""
    from pigp_torch.data.sampling import generate_dataset
    from pigp_torch.prior import log_excess_hessian
    from pigp_torch.surrogate import train_ensemble

    t = time.perf_counter()
    data = generate_dataset(sim, 100_000, seed=0, progress=False)
    surrogate, reports = train_ensemble(data, n_members=3, progress=False)
    H, _, _ = log_excess_hessian(surrogate, x, sim.loss_background)
    S = (-H / 2).detach().numpy()
    exact = model_precision(sim)
    m = fidelity(S, P, names)
    err = max(r["val_rel_rmse"] for r in reports)
    dist = float(np.linalg.norm(S - exact) / np.linalg.norm(exact))
    print(f"  surrogate: held-out rel. RMSE <= {100 * err:.2f} %, |S - S_exact|/|S_exact| "
          f"{dist:.3f}, cos {m['cosines'][0]:.3f} {m['cosines'][1]:.3f} {m['cosines'][2]:.3f}, "
          f"r_diag {m['r_diag']:.3f}, r_off {m['r_offdiag']:.3f}, min n/n+9 corr "
          f"{min(m['pair_corr']):.2f}, cond {m['condition']:.0f} "
          f"({time.perf_counter() - t:.0f} s)", flush=True)  # fmt: skip


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", default="1001-1040", help="error seeds, a-b (default 1001-1040)")
    p.add_argument("--optics", default="user", help="SPEAR3 deck (default user)")
    p.add_argument("--surrogate", action="store_true", help="also train surrogates (~min each)")
    args = p.parse_args(argv)
    a, b = (int(v) for v in args.seeds.split("-"))
    names, P = authors_precision()
    rows = []
    print("seed  scale  max|x|/A  ratio@opt%  f*  cos1 cos2 cos3  r_diag r_off  cond  s")
    for seed in range(a, b + 1):
        t = time.perf_counter()
        sim = Spear3Coupling(seed, optics=args.optics)
        x, f = sim.optimum()
        r = sim.evaluate(x)
        m = fidelity(model_precision(sim), P, names)
        row = (seed, sim.error_scale, float(x.abs().max()), 100 * float(r.eps_y / r.eps_x), f,
               *m["cosines"], m["r_diag"], m["r_offdiag"], m["condition"])  # fmt: skip
        rows.append(row)
        fmt = "{:4d}  {:5.2f}  {:6.2f}  {:8.3f}  {:5.3f}  " + "{:.3f} " * 5 + " {:5.0f}  {:.0f}"
        print(fmt.format(*row, time.perf_counter() - t), flush=True)
        if args.surrogate:
            surrogate_row(sim, x, P, names)
    A = np.array(rows)
    inside = float(np.mean(A[:, 2] < 30.0 * 0.999))
    for k, name in ((1, "error scale"), (2, "max |knob| at the optimum (A)"),
                    (3, "eps_y/eps_x at the optimum (%)"), (10, "condition number")):  # fmt: skip
        q = np.percentile(A[:, k], [0, 25, 50, 75, 100])
        print(f"{name}: min {q[0]:.3g}, IQR {q[1]:.3g}-{q[3]:.3g}, median {q[2]:.3g}, "
              f"max {q[4]:.3g}")  # fmt: skip
    print(f"optima inside ±30 A: {inside:.0%} of {len(A)}")
    print(
        f"cos3 >= 0.95: {np.mean(A[:, 7] >= 0.95):.0%}; r_diag >= 0.9: "
        f"{np.mean(A[:, 8] >= 0.9):.0%}; r_off >= 0.9: {np.mean(A[:, 9] >= 0.9):.0%}"
    )
    return 0


if __name__ == "__main__":
    torch.set_num_threads(1)
    sys.exit(main())
