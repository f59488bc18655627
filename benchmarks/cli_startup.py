r"""CPU time of the ``pigp`` commands a new user meets first, and of ``pigp report``.

``python benchmarks/cli_startup.py``: each command runs as a child process
(``python -m pigp_torch.cli ...``, what the ``pigp`` script runs) ``--repeats`` times; printed
is the median CPU time of the child (user + system, seconds, from
``resource.getrusage(RUSAGE_CHILDREN)`` before and after), with the median wall time beside it:

* ``pigp --help``;
* ``pigp optimize`` without ``--config`` (a usage error, exit 2);
* ``pigp optimize --config TYPO.yaml``: ``examples/run_sim.yaml`` with ``budget`` misspelt (a
  run-file error, exit 2);
* ``pigp report LOG`` of the README's 150-evaluation SPEAR3 run (``--log``; default: the run is
  made first, ``pigp optimize --config examples/run_sim.yaml`` in a temporary folder);
* ``pigp report FOLDER`` of a ``pigp compare`` folder (``--compare``; default: a synthetic
  ``runs.csv`` of the size ``pigp compare``'s defaults write: 8 methods on 24 machines, 100
  evaluations for the GP methods and 300 for Nelder-Mead and RCDS, 13 knobs).

``--report-repeats`` (default 3) sets the repeats of the two reports. CPU time, unlike wall
time, hardly depends on what else the machine runs; to see the busy case, run e.g. two
``yes > /dev/null &`` alongside (and stop them after).
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def child_times(argv: list[str], cwd: Path, expect: int) -> tuple[float, float]:
    """Run ``pigp ARGV`` once; return (CPU seconds of the child, user + system; wall seconds).

    Raises:
        RuntimeError: the exit status is not ``expect``.
    """
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-m", "pigp_torch.cli", *argv], cwd=cwd, capture_output=True, text=True
    )
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != expect:
        raise RuntimeError(f"pigp {' '.join(argv)}: exit {proc.returncode}: {proc.stderr[-500:]}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return cpu, wall


def measure(label: str, argv: list[str], cwd: Path, repeats: int, expect: int = 0) -> None:
    """Print the median CPU and wall seconds of ``repeats`` runs of ``pigp ARGV``."""
    runs = [child_times(argv, cwd, expect) for _ in range(repeats)]
    cpu = statistics.median(c for c, _ in runs)
    wall = statistics.median(w for _, w in runs)
    print(f"{label:<44} {cpu:8.2f} s CPU {wall:8.2f} s wall  (median of {repeats})", flush=True)


def readme_run(folder: Path) -> Path:
    """The README's run, ``pigp optimize --config examples/run_sim.yaml``, in ``folder``; returns
    its run log."""
    (folder / "examples").mkdir()
    shutil.copy(ROOT / "examples" / "run_sim.yaml", folder / "examples")
    print("making the README's 150-evaluation run (pigp optimize, about a minute) ...", flush=True)
    child_times(["optimize", "--config", "examples/run_sim.yaml", "--quiet"], folder, 0)
    return folder / "runs" / "run_sim.jsonl"


def synthetic_compare(folder: Path) -> Path:
    """A ``runs.csv`` of ``pigp compare``'s default size and columns (values drawn at random)."""
    import numpy as np
    import pandas as pd

    rng = np.random.default_rng(0)
    knobs = [f"k{i:02d}" for i in range(13)]
    budgets = {"pigp-physics": 100, "pigp": 100, "pigp-zero-mean": 100, "ml2": 100}
    budgets |= {"xopt-ucb": 100, "pigp-fast": 100, "nelder-mead": 300, "rcds": 300}
    frames = []
    for method, budget in budgets.items():
        for seed in range(1, 25):
            f_true = 0.5 + 1.2 * (1 - np.exp(-np.arange(budget) / 30)) * rng.uniform(0.6, 1, budget)
            best = np.maximum.accumulate(f_true)
            frame = pd.DataFrame(rng.uniform(-30, 30, (budget, 13)), columns=knobs)
            frame.insert(0, "machine_seed", seed)
            frame.insert(0, "step", np.arange(budget))
            frame["y"] = f_true + rng.normal(0, 0.04, budget)
            frame["method"] = method
            frame["f_true"], frame["best_f_true"] = f_true, best
            frame["f0"], frame["f_star"] = f_true[0], 1.7
            frame["gain_fraction"] = (best - f_true[0]) / (1.7 - f_true[0])
            frames.append(frame)
    folder.mkdir()
    pd.concat(frames).to_csv(folder / "runs.csv", index=False)
    return folder


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--repeats", type=int, default=5, help="runs of each start-up command")
    p.add_argument("--report-repeats", type=int, default=3, help="runs of each report")
    p.add_argument("--log", type=Path, help="run log to report (default: make the README's)")
    p.add_argument("--compare", type=Path, help="compare folder (default: a synthetic one)")
    p.add_argument("--no-report", action="store_true", help="only the start-up commands")
    a = p.parse_args()
    env_threads = os.environ.get("OMP_NUM_THREADS", "unset")
    print(f"CPU time of child processes; OMP_NUM_THREADS={env_threads}; {os.cpu_count()} CPUs; "
          f"load average {os.getloadavg()[0]:.2f}", flush=True)  # fmt: skip
    with tempfile.TemporaryDirectory(prefix="pigp-cli-bench-") as tmp:
        tmp = Path(tmp)
        typo = tmp / "typo.yaml"
        text = (ROOT / "examples" / "run_sim.yaml").read_text(encoding="utf-8")
        typo.write_text(text.replace("\nbudget:", "\nbudgte:"), encoding="utf-8")
        measure("pigp --help", ["--help"], tmp, a.repeats)
        measure("pigp optimize (no --config: usage error)", ["optimize"], tmp, a.repeats, 2)
        argv = ["optimize", "--config", str(typo)]
        measure("pigp optimize --config TYPO.yaml (exit 2)", argv, tmp, a.repeats, 2)
        if a.no_report:
            return
        log = a.log.resolve() if a.log else readme_run(tmp / "run")
        out = tmp / "report"
        measure("pigp report LOG (150-evaluation SPEAR3 run)", ["report", str(log), "-o",
                str(out)], tmp, a.report_repeats)  # fmt: skip
        folder = a.compare.resolve() if a.compare else synthetic_compare(tmp / "compare")
        measure("pigp report FOLDER (compare folder)", ["report", str(folder), "-o", str(out)],
                tmp, a.report_repeats)  # fmt: skip


if __name__ == "__main__":
    main()
