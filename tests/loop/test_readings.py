"""Plausible readings (pigp_torch.loop.readings): the physical range, the re-read of a reading
far from the run's own, a genuine improvement kept, and the best point confirmed at the end."""

from __future__ import annotations

import math

import pytest
import torch

from pigp_torch.data.runlog import read_log
from pigp_torch.loop import optimize
from pigp_torch.loop.readings import (
    AGREE_A,
    OUTLIER_K,
    ReadingJudge,
    confirm_best,
    plausible_reading,
)
from pigp_torch.machine import GuardedMachine
from tests.loop.problems import BOUNDS, D
from tests.loop.test_safety import INITIAL, Walk

SIGMA = 0.01


class Scripted(GuardedMachine):
    """Reads ``base(x) + noise`` with the noise from a seeded generator; ``glitches`` maps a
    read number (1-based) to the value returned instead."""

    def __init__(self, glitches=None, jump_at=None):
        super().__init__(BOUNDS, ["qs1", "qs2"], x_init=list(INITIAL))
        self.glitches = dict(glitches or {})
        self.jump_at = jump_at
        self.n_reads = 0
        self.g = torch.Generator().manual_seed(0)

    def _apply(self, x):
        pass

    def base(self, x) -> float:
        return 1.0 + float(x.sum())

    def read(self):
        self.n_reads += 1
        if self.n_reads in self.glitches:
            return self.glitches[self.n_reads]
        return self.base(self._x) + SIGMA * float(torch.randn((), generator=self.g, dtype=D))


def test_the_rule_in_numbers():
    """Range and finiteness make a reading invalid; with sigma stated, a reading more than
    k = 5 robust sigmas from the median needs a re-read, which must agree within 4 sqrt(2) sigma."""
    j = ReadingJudge(noise=SIGMA, objective_range=(0.0, 10.0))
    assert "outside the objective range" in j.invalid(1e30)
    assert "non-finite" in j.invalid(float("nan")) and j.invalid(5.0) is None
    assert "first reading" in j.suspicious(1.0)  # nothing to compare with yet: re-read
    for y in [1.0, 1.0 + SIGMA, 1.0 - SIGMA, 1.0, 1.0 + 2 * SIGMA]:
        j.accept(y)
    # MAD of these five is sigma, 1.4826 MAD > sigma: s = 1.4826 sigma
    s = 1.4826 * SIGMA
    assert j.scale() == pytest.approx(s)
    assert j.suspicious(1.0 + OUTLIER_K * s * 0.99) is None
    assert j.suspicious(1.0 + OUTLIER_K * s * 1.01) is not None
    assert j.agreement_tolerance() == pytest.approx(AGREE_A * 2**0.5 * SIGMA)
    assert ReadingJudge(noise=None).suspicious(1e6) is None  # no stated noise: no outlier rule


def test_a_glitch_is_reread_and_a_real_jump_is_kept():
    """The first reading is read twice (kept as the mean: they agree); a one-off 50 (inside
    the range) is discarded after its re-read; a real jump of 30 sigma that repeats is kept, as
    the mean of the two readings."""
    seq = iter([1.0, 1.0, 1.01, 0.99, 1.0, 1.0, 50.0, 1.005, 1.30, 1.31])
    discarded = []
    j = ReadingJudge(noise=SIGMA, objective_range=(0.0, 100.0))
    ys = [plausible_reading(lambda: next(seq), j, 2, 0.0, lambda r, y: discarded.append(y))
          for _ in range(7)]  # fmt: skip
    assert ys[:5] == [(1.0, 2), (1.01, 1), (0.99, 1), (1.0, 1), (1.0, 1)]
    assert ys[5] == (1.005, 2) and discarded == [50.0]
    assert ys[6] == (pytest.approx(1.305), 2) and discarded == [50.0]


def test_a_glitch_never_becomes_the_best_of_a_run(tmp_path):
    """+1e30 (outside objective_range) and +50 (inside, stated noise) in a run: both
    discarded and logged, neither an evaluation nor the best; restore='best' confirms the best
    point by fresh readings and stays there."""
    m = Scripted(glitches={3: 1e30, 6: 50.0})
    table = optimize(
        m, Walk(BOUNDS, step=0.05), None, 8, log=tmp_path / "r.jsonl", restore="best",
        noise=SIGMA, objective_range=(0.0, 100.0),
    )  # fmt: skip
    log = read_log(tmp_path / "r.jsonl")
    assert [d["y"] for d in log.discarded] == [1e30, 50.0]
    assert float(table["y"].max()) < 5.0
    end = log.last_end
    assert end["restored_to"] == "best (confirmed)" and end["best"]["y"] < 5.0
    assert m.get().tolist() == pytest.approx(end["best"]["x"])


def test_an_unconfirmed_best_restores_the_initial_knobs(tmp_path):
    """A glitch that repeats on its re-read becomes an evaluation and the best; at the end the
    fresh readings there do not reproduce it, and the initial knobs are restored instead."""
    m = Scripted(glitches={4: 50.0, 5: 50.0})
    with pytest.warns(UserWarning, match="the best point did not reproduce"):
        optimize(m, Walk(BOUNDS, step=0.05), None, 6, log=tmp_path / "r.jsonl", restore="best",
                 noise=SIGMA)  # fmt: skip
    records = read_log(tmp_path / "r.jsonl")
    end = records.last_end
    assert end["rejected_best"]["y"] == 50.0 and end["best"] is None
    assert end["control_reading"]["confirmed"] is True  # the start point still reads the same
    assert end["best_confirmation"]["confirmed"] is False
    assert end["restored_to"] == "initial (best not confirmed)" and m.get().tolist() == INITIAL
    from pigp_torch.reporting.report import _notices

    notices = _notices(records, records.X(), None, ["qs1", "qs2"])
    step = end["rejected_best"]["step"] + 1
    assert f"evaluation {step}: the best point did not reproduce" in "\n".join(notices)


def test_the_first_reading_is_reread_when_the_noise_is_stated():
    """The run's first reading has nothing to compare with: with sigma stated it is read again
    and kept only if the two agree; a 50 followed by two agreeing readings of 1.0 is discarded
    (logged), and never becomes a reading of the run. Without sigma it is read once."""
    seq = iter([50.0, 1.0, 1.0 + SIGMA])
    discarded = []
    j = ReadingJudge(noise=SIGMA, objective_range=(0.0, 100.0))
    y, reads = plausible_reading(lambda: next(seq), j, 2, 0.0, lambda r, y: discarded.append(y))
    assert (y, reads) == (pytest.approx(1.0 + SIGMA / 2), 3) and discarded == [50.0]
    assert j.readings == [pytest.approx(1.0 + SIGMA / 2)]
    seq = iter([50.0, 1.0])
    assert plausible_reading(lambda: next(seq), ReadingJudge(), 2, 0.0, print) == (50.0, 1)


def test_a_glitch_on_the_first_evaluation_is_never_the_best(tmp_path):
    """A 50 on the very first read of a run with the noise stated is discarded (logged) and the
    first evaluation is the mean of the two agreeing reads that follow."""
    m = Scripted(glitches={1: 50.0})
    table = optimize(m, Walk(BOUNDS, step=0.05), None, 6, log=tmp_path / "r.jsonl",
                     noise=SIGMA, objective_range=(0.0, 100.0))  # fmt: skip
    log = read_log(tmp_path / "r.jsonl")
    assert [d["y"] for d in log.discarded] == [50.0] and log.discarded[0]["step"] == 0
    assert float(table["y"].max()) < 5.0 and log.evaluations[0]["reads"] == 3


def test_confirm_best_tolerance():
    """Confirmed iff the mean of 3 fresh readings is within sigma (sqrt(2 ln N) + 4 sqrt(1 +
    1/3)) of the best of N readings in EITHER direction (a best that reads far better than
    logged is not confirmed either), and the 3 readings agree with each other (range <= 4
    sqrt(2) sigma); minimize mirrored."""
    j = ReadingJudge(noise=SIGMA)
    tol = 4 * SIGMA * (4 / 3) ** 0.5
    assert confirm_best(lambda: 1.0 - 0.99 * tol, 1.0, j, True)["confirmed"]
    assert not confirm_best(lambda: 1.0 - 1.01 * tol, 1.0, j, True)["confirmed"]
    assert confirm_best(lambda: 1.0 + 0.99 * tol, 1.0, j, True)["confirmed"]
    assert not confirm_best(lambda: 1.0 + 1.01 * tol, 1.0, j, True)["confirmed"]
    assert not confirm_best(lambda: 1.0 + 1.01 * tol, 1.0, j, False)["confirmed"]
    assert not confirm_best(lambda: 1.0 - 1.01 * tol, 1.0, j, False)["confirmed"]
    # 100 sigma above the best: not a confirmation
    assert not confirm_best(lambda: 1.0 + 100 * SIGMA, 1.0, j, True)["confirmed"]
    # the mean agrees but the readings do not agree with each other
    spread = iter([1.0 - 3 * SIGMA, 1.0, 1.0 + 3 * SIGMA])  # range 6 sigma > 4 sqrt(2) sigma
    out = confirm_best(lambda: next(spread), 1.0, j, True)
    assert out["mean"] == pytest.approx(1.0) and not out["confirmed"]
    assert out["spread"] == pytest.approx(6 * SIGMA)
    close = iter([1.0 - 2.8 * SIGMA, 1.0, 1.0 + 2.8 * SIGMA])  # range 5.6 sigma < 5.66 sigma
    assert confirm_best(lambda: next(close), 1.0, j, True)["confirmed"]
    # after N = 100 readings the best is read high by up to sqrt(2 ln N) sigma: allowed for
    j100 = ReadingJudge(noise=SIGMA, readings=[1.0] * 100)
    tol100 = SIGMA * ((2 * math.log(100)) ** 0.5 + 4 * (4 / 3) ** 0.5)
    assert confirm_best(lambda: 1.0 - 0.99 * tol100, 1.0, j100, True)["confirmed"]
    assert not confirm_best(lambda: 1.0 - 1.01 * tol100, 1.0, j100, True)["confirmed"]


def test_a_control_reading_that_changed_rejects_the_best(tmp_path):
    """A sustained glitch: every read from the 8th on returns 50 (its re-reads agree, so it
    becomes evaluations and the best). With restore='best' the knobs first go to the first
    evaluation's point (the initial knobs), whose fresh reading (50) is far from its logged
    value: the run says so, stays at the initial knobs, and reports no best."""
    m = Scripted(glitches={k: 50.0 for k in range(8, 40)})
    with pytest.warns(UserWarning, match="the machine or its instrument changed"):
        optimize(m, Walk(BOUNDS, step=0.05), None, 8, log=tmp_path / "r.jsonl", restore="best",
                 noise=SIGMA)  # fmt: skip
    records = read_log(tmp_path / "r.jsonl")
    end = records.last_end
    assert end["rejected_best"]["y"] == 50.0 and end["best"] is None
    assert end["control_reading"]["confirmed"] is False and "best_confirmation" not in end
    assert end["restored_to"] == "initial (best not confirmed)" and m.get().tolist() == INITIAL


def test_a_genuine_optimization_is_not_taken_for_glitches(tmp_path):
    """Nelder-Mead on the simulated SPEAR3 ring (noise 0.04 mA/min, stated) climbs by more than
    20 sigma in 150 evaluations; the re-read rule discards none of its readings and costs a few
    extra reads (here <= 5 % of the evaluations)."""
    from pigp_torch.machine import SimulatedMachine
    from pigp_torch.optimizers import NelderMead
    from pigp_torch.simulation import Spear3Coupling

    ring = Spear3Coupling(1)
    m = SimulatedMachine(ring, noise=0.04, seed=0)
    table = optimize(m, NelderMead(ring.bounds, initial_simplex_size=0.2), None, 150,
                     noise=0.04, log=tmp_path / "r.jsonl")  # fmt: skip
    log = read_log(tmp_path / "r.jsonl")
    f = ring.loss_rate(torch.tensor(table[list(ring.knob_names)].to_numpy(), dtype=D))
    assert float(f.max() - f[0]) > 20 * 0.04
    assert log.discarded == []
    extra = sum(e["reads"] for e in log.evaluations) - len(table)
    assert 0 <= extra <= 0.05 * len(table)
