r"""Figures of a drifting machine: gain (SPEAR3) or true MAE (ARES) against reading, with the
unknowns the default method tracks (docs/drift_families.md).

The top panel draws the per-reading tables written by ``benchmarks/drift_bench.py --csv``
(one line per method: the mean over machines, thin lines per machine). The SPEAR3 gain is
:math:`(f_t(x_t) - f_t(0)) / (f^*_t - f_t(0))` against the moving optimum. For SPEAR3,
``--track SEED`` also runs ``pigp-physics`` on that tuning machine of the family and draws what
it tracks next to the truth: the fitted peak against the true moving optimum :math:`f^*_t`
(mA/min), the travel of its fitted optimum (``recommend()``) since reading
:data:`TRAVEL_FROM` against the true optimum's, :math:`\lVert\delta(t) - \delta(100)\rVert`
(A), and the readings the fit remembers (its learned memory). ``--track-csv`` saves (or, when
it exists, reuses) that run.

    python benchmarks/drift_figure.py spear3 --csv ring.csv --family drift --track 101 \
        --prior docs/data/prior_spear3_seed0_exact.json --track-csv track101.csv \
        -o docs/figures/drift_spear3.png
    python benchmarks/drift_figure.py ares --csv ares.csv --family drift --track 0 \
        --readings 300 --track-csv track0.csv -o docs/figures/drift_ares.png

For ARES, ``--track TRIAL`` runs ``ares-physics`` on that tuning trial of the family and draws
the beam centroid at the screen that its tracked model predicts at one fixed setting (the run's
last) against the drifting machine's at that setting (µm), and the true MAE of that run.
"""

from __future__ import annotations

import argparse
import os
import sys

import pandas as pd
import torch

COLUMNS = {"spear3": ("gain", "gain (fraction)"),
           "ares": ("mae_true_um", "true MAE (µm)")}  # fmt: skip
#: Readings of the moving average of each method's mean line (the thin lines are raw).
SMOOTH = 10


#: The reading from which the optimum's travel is drawn (the fit has converged by then).
TRAVEL_FROM = 100


class Recorder:
    """An ask/tell optimizer that records its ``tracked()`` unknowns and its ``recommend()``
    (the fitted optimum, ``d``) after every tell."""

    def __init__(self, optimizer, optima: bool = True) -> None:
        self.optimizer, self.rows, self.optima = optimizer, [], []
        self.uses_observables = optimizer.uses_observables
        self.record_optima = optima  # off where recommend() is an ask (the ARES tracker's)
        self.states: list[tuple[torch.Tensor, torch.Tensor | None]] = []  # (theta, offset)

    def ask(self):
        return self.optimizer.ask()

    def tell(self, x, y, **kwargs) -> None:
        self.optimizer.tell(x, y, **kwargs)
        for name, (value, unit) in self.optimizer.tracked().items():
            self.rows.append((len(self.optimizer.Y) - 1, name, value, unit))
        if self.record_optima:
            self.optima.append(self.optimizer.recommend().detach().clone())
        else:  # a fitted-model optimizer: its unknowns and offset now
            offset = self.optimizer.offset
            self.states.append((self.optimizer.theta.clone(), None if offset is None else
                                offset.clone()))  # fmt: skip

    def recommend(self):
        return self.optimizer.recommend()


def track_run(seed: int, family: str, readings: int, prior_path: str | None) -> pd.DataFrame:
    """``pigp-physics`` on tuning machine ``seed`` of ``family``: per reading its tracked
    unknowns and the truth (``reading, name, value, unit``)."""
    from pigp_torch._utils import DTYPE, default_dtype
    from pigp_torch.bench.protocol import run_seed
    from pigp_torch.machines import KINDS
    from pigp_torch.machines.drift import drive
    from pigp_torch.machines.ring.drift import gain_series
    from pigp_torch.methods import METHODS, RunContext
    from pigp_torch.prior import PhysicsPrior

    prior = PhysicsPrior.load(prior_path) if prior_path else None
    machine = KINDS["spear3"].drift_machine(family=family, seed=seed, noise=0.04)
    ctx = RunContext(machine=machine, prior=prior, seed=run_seed("pigp-physics", seed),
                     noise=0.04, archive_size=0)  # fmt: skip
    with torch.random.fork_rng(devices=[]), default_dtype(DTYPE):
        torch.manual_seed(run_seed("pigp-physics", seed))
        recorder = Recorder(METHODS["pigp-physics"].build(ctx))
        X, _ = drive(machine, recorder, readings, set_back=False)
        _, f_star = gain_series(machine, X)
    K, ref = X.shape[1], min(TRAVEL_FROM, readings - 1)
    delta = torch.stack([machine.theta_at(t)[:K] for t in range(readings)])
    travel = torch.linalg.vector_norm(delta - delta[ref], dim=1).numpy()  # the optimum is x* - δ
    fitted = torch.stack(recorder.optima)
    moved = torch.linalg.vector_norm(fitted - fitted[ref], dim=1).numpy()
    rows = [r for r in recorder.rows if r[1] != "centre_moved"]
    rows += [(t, "optimum_moved", float(moved[t]), "A") for t in range(ref, readings)]
    rows += [(t, "true_peak", float(f_star[t]), "mA/min") for t in range(readings)]
    rows += [(t, "true_optimum_moved", float(travel[t]), "A") for t in range(ref, readings)]
    return pd.DataFrame(rows, columns=["reading", "name", "value", "unit"])


def ares_track_run(trial: int, family: str, readings: int) -> pd.DataFrame:
    """``ares-physics`` on tuning trial ``trial`` of ``family`` (draw seed 101, noise-free
    screen, as ``drift_bench.py``): per reading the beam centroid at the screen that its tracked
    model (unknowns and offset after that reading) predicts at one fixed setting, the run's last
    (``model_mu_x``, ``model_mu_y``), the true machine's centroid at that setting at that
    reading (``true_mu_x``, ``true_mu_y``; the drifting incoming beam, no magnet play), and the
    run's true MAE, all in µm (``reading, name, value, unit``). The unknowns themselves are not
    drawn: the incoming centroid and the screen's misalignment move the beam alike, so the
    tracker may carry a drift in either; the beam they predict is what it follows."""
    from pigp_torch._utils import DTYPE, default_dtype
    from pigp_torch.machines import KINDS
    from pigp_torch.machines.ares_ea.methods import ares_objective_for
    from pigp_torch.machines.drift import drive
    from pigp_torch.methods import METHODS, RunContext

    seed = 101
    machine = KINDS["ares-ea"].drift_machine(
        family=family, seed=seed, trial=trial, objective=ares_objective_for("ares-physics")
    )
    ctx = RunContext(machine=machine, prior=None, seed=seed + trial, archive_size=0,
                     noise=None, maximize=machine.maximize)  # fmt: skip
    with torch.random.fork_rng(devices=[]), default_dtype(DTYPE):
        torch.manual_seed(seed + trial)
        optimizer = METHODS["ares-physics"].build(ctx)
        recorder = Recorder(optimizer, optima=False)
        X, true = drive(machine, recorder, readings, set_back=False)
        x_ref = X[-1][None]
        with torch.no_grad():
            model = torch.stack([
                optimizer.machine_model.observe(x_ref, theta)[0]
                + (0.0 if offset is None else offset)
                for theta, offset in recorder.states
            ])  # fmt: skip
            truth = torch.stack([
                machine.segment.observe(x_ref, machine.incoming_at(t),
                                        machine.trial.misalignments)[0]
                for t in range(readings)
            ])  # fmt: skip
    mae = ((true - machine.target).abs().mean(-1) * 1e6).tolist()
    rows = [(t, "mae_true", m, "µm") for t, m in enumerate(mae)]
    for j, name in ((0, "mu_x"), (2, "mu_y")):
        rows += [(t, f"model_{name}", 1e6 * float(model[t, j]), "µm") for t in range(readings)]
        rows += [(t, f"true_{name}", 1e6 * float(truth[t, j]), "µm") for t in range(readings)]
    return pd.DataFrame(rows, columns=["reading", "name", "value", "unit"])


#: The tracked panels per kind: (the method's series, its label, the truth's series, its
#: label, the axis label).
PANELS = {
    "spear3": (("peak", "pigp-physics", "true_peak", "true", "peak (mA/min)"),
               ("optimum_moved", "pigp-physics", "true_optimum_moved", "true",
                f"travel since {TRAVEL_FROM} (A)"),
               ("remembered", "pigp-physics", None, None, "readings remembered")),
    "ares": (("model_mu_x", "tracked model (ares-physics)", "true_mu_x", "true",
              "μx at the screen (µm)"),
             ("model_mu_y", "tracked model (ares-physics)", "true_mu_y", "true",
              "μy at the screen (µm)"),
             ("mae_true", "true MAE of this run", None, None, "MAE (µm)")),
}  # fmt: skip


def draw(runs: pd.DataFrame, kind: str, track: pd.DataFrame | None, title: str, out: str):
    """Write the figure: the score per method against reading, then the tracked unknowns."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    col, label = COLUMNS[kind]
    pairs = PANELS[kind]
    rows = 1 + (len(pairs) if track is not None else 0)
    fig, axes = plt.subplots(rows, 1, figsize=(8, 2.6 * rows), sharex=True, squeeze=False)
    ax = axes[0, 0]
    for i, (method, g) in enumerate(runs.groupby("method", sort=False)):
        table = g.pivot(index="reading", columns="id", values=col)
        ax.plot(table.index, table.values, color=f"C{i}", lw=0.4, alpha=0.4)
        mean = table.mean(axis=1).rolling(SMOOTH, min_periods=1).mean()
        ax.plot(table.index, mean, color=f"C{i}", lw=1.5,
                label=f"{method} (mean of {table.shape[1]}, {SMOOTH}-reading average)")  # fmt: skip
    ax.set_ylabel(label)
    ax.set_yscale("log" if kind == "ares" else "linear")
    ax.set_title(title)
    ax.legend(fontsize=8)
    for ax, (name, label, true, true_label, ylabel) in zip(
        axes[1:, 0], pairs[: rows - 1], strict=True
    ):
        for who, what, style in ((name, label, "-"), (true, true_label, "--")):
            part = track[track.name == who] if who else None
            if part is not None and len(part):
                ax.plot(part.reading, part.value, style, label=what)
        ax.set_ylabel(ylabel)
        ax.legend(fontsize=8)
    axes[-1, 0].set_xlabel("reading")
    fig.tight_layout()
    fig.savefig(out, dpi=120)
    plt.close(fig)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("kind", choices=sorted(COLUMNS))
    p.add_argument("--csv", nargs="+", required=True, help="tables of drift_bench.py --csv")
    p.add_argument("--family", default="drift", help="the family the tables ran (title)")
    p.add_argument(
        "--track",
        type=int,
        default=None,
        help="the tuning machine (SPEAR3, 101+) or trial (ARES, 0-49) to track",
    )
    p.add_argument("--readings", type=int, default=500)
    p.add_argument("--prior", default=None, help="SPEAR3: a saved prior for --track")
    p.add_argument("--track-csv", default=None, help="save / reuse the --track run")
    p.add_argument("-o", "--out", required=True, help="PNG to write")
    a = p.parse_args(argv)
    try:
        runs = pd.concat([pd.read_csv(path) for path in a.csv], ignore_index=True)
        if COLUMNS[a.kind][0] not in runs:
            raise ValueError(f"the tables have no column {COLUMNS[a.kind][0]!r} ({a.kind})")
        track = None
        if a.track is not None:
            tuning = range(101, 10**6) if a.kind == "spear3" else range(0, 50)
            if a.track not in tuning:
                raise ValueError(f"{a.track} is held out: track a tuning one ({tuning.start}+,"
                                 f" below {tuning.stop})")  # fmt: skip
            if a.track_csv and os.path.exists(a.track_csv):
                track = pd.read_csv(a.track_csv)
            elif a.kind == "spear3":
                track = track_run(a.track, a.family, a.readings, a.prior)
            else:
                track = ares_track_run(a.track, a.family, a.readings)
            if a.track_csv and not os.path.exists(a.track_csv):
                track.to_csv(a.track_csv, index=False)
        title = f"{a.kind} family {a.family}"
        what = "machine" if a.kind == "spear3" else "trial"
        title += f", tracked: {what} {a.track}" if track is not None else ""
        draw(runs, a.kind, track, title, a.out)
    except (OSError, ValueError, KeyError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
