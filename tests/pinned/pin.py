r"""Pinned benchmark trajectories: the proposals of the registered methods, to the bit.

A run is :func:`pigp_torch.bench.protocol.run_one` (the spear3-13 protocol, the machine's own
loss-rate map, no :math:`f^*` search) with the kept prior ``docs/data/prior_spear3_seed0_surrogate
.json`` (it has the error-ensemble fields, so ``pigp-physics`` uses them). :data:`RUNS` lists
``(method, options, machine seed, budget)``; every evaluated setting and reading is stored as
float64 hex strings in ``tests/data/pinned_trajectories.json``.

The runs are made in a new process on the CPU-independent path of :mod:`tests.pinned.portable`
(scalar kernels, one BLAS branch), so the pins hold on any x86-64 CPU and still catch any change
of the arithmetic. Regenerate (only on purpose, on unchanged code): ``python -m tests.pinned.pin``
(it re-runs itself on that path); ``python -m tests.pinned.pin --print KEY`` prints one run.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

from tests.pinned.portable import MARKER, run_portable

ROOT = Path(__file__).resolve().parents[2]
PRIOR = ROOT / "docs" / "data" / "prior_spear3_seed0_surrogate.json"
DATA = ROOT / "tests" / "data" / "pinned_trajectories.json"

#: (method, options over the registered spec, machine seed, evaluations). The first two run in
#: the default test pass; the others are slow.
RUNS = (
    ("pigp-fast", {}, 101, 30),
    ("pigp-physics", {}, 101, 40),
    ("pigp-physics", {}, 102, 40),
    ("pigp-fast", {}, 102, 30),
    ("pigp-fast", {"acquisition": "logei"}, 101, 20),
    ("pigp-fast", {"acquisition": "ei", "trust_center": "best_mean"}, 102, 20),
    ("pigp-physics", {"center_prior": "box", "shape_prior": "model"}, 101, 40),
    ("pigp-physics", {"travel_limit": 0.2}, 102, 30),
    ("pigp", {}, 101, 30),
    ("pigp", {}, 102, 30),
    ("pigp", {"mean": "zero", "acquisition": "logei"}, 101, 20),
    ("ml2", {}, 101, 30),
    ("nelder-mead", {}, 101, 30),
    ("rcds", {}, 101, 30),
)


def run_key(method: str, options: dict, seed: int, budget: int) -> str:
    opts = ",".join(f"{k}={options[k]}" for k in sorted(options))
    return f"{method}[{opts}]|{seed}|{budget}"


def trajectory(method: str, options: dict, seed: int, budget: int) -> dict:
    """One run's evaluated settings ``X`` (``budget x d``) and readings ``y`` as hex floats."""
    from pigp_torch.bench.protocol import run_one
    from pigp_torch.methods import METHODS
    from pigp_torch.prior import PhysicsPrior

    prior = PhysicsPrior.load(PRIOR)
    spec = METHODS[method].with_options(**options) if options else METHODS[method]
    table = run_one(spec, seed, prior, budget=budget, optimum_starts=0)
    X = table[list(prior.knob_names)].to_numpy()
    return {
        "X": [[float(v).hex() for v in row] for row in X],
        "y": [float(v).hex() for v in table["y"].to_numpy()],
        "notice": [str(v) for v in table["notice"]],
    }


def run_by_key(key: str) -> tuple:
    """The entry of :data:`RUNS` whose :func:`run_key` is ``key``."""
    runs = {run_key(*run): run for run in RUNS}
    if key not in runs:
        raise KeyError(f"no pinned run {key!r}; known: {', '.join(runs)}")
    return runs[key]


def portable_trajectory(run, *, prefix=(), portable: bool = True) -> dict:
    """:func:`trajectory` of ``run`` (a key of :data:`RUNS` or a ``(method, options, seed,
    budget)`` tuple), computed in a new process on the portable path."""
    arg = ["--print", run] if isinstance(run, str) else ["--run", json.dumps(list(run))]
    out = run_portable(["-m", "tests.pinned.pin", *arg], prefix=prefix, portable=portable)
    return json.loads(out.strip().splitlines()[-1])


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description="Pinned benchmark trajectories.")
    parser.add_argument("--print", metavar="KEY", help="print one pinned run's trajectory as JSON")
    parser.add_argument("--run", metavar="JSON", help="print [method, options, seed, budget]'s")
    args = parser.parse_args(argv)
    if args.print or args.run:
        run = run_by_key(args.print) if args.print else json.loads(args.run)
        print(json.dumps(trajectory(*run)))
        return
    if os.environ.get(MARKER) != "1":
        print(run_portable(["-m", "tests.pinned.pin"]), end="")
        return
    out = {run_key(*run): trajectory(*run) for run in RUNS}
    DATA.write_text(json.dumps(out, indent=0) + "\n")
    print(f"wrote {len(out)} runs to {DATA} on the portable path")


if __name__ == "__main__":
    main()
