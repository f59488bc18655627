"""The noise of a run that states none (pigp_torch.loop.noise): measured at the start from a
few readings at the initial setting, floored, logged in the start record, reused on a resume;
and the best point never kept where it reads worse than the start (readings.below_start)."""

from __future__ import annotations

import pytest
import torch

from pigp_torch.data.runlog import read_log
from pigp_torch.loop import optimize
from pigp_torch.loop.noise import NOISE_FLOOR_ABS, NOISE_FLOOR_REL, estimate_noise
from pigp_torch.loop.options import RunOptions
from pigp_torch.loop.readings import below_start
from pigp_torch.machine import GuardedMachine
from tests.loop.problems import BOUNDS, D
from tests.loop.test_readings import SIGMA, Scripted
from tests.loop.test_safety import INITIAL, Walk


def test_the_noise_estimate_in_numbers():
    """sigma = max(sample std, 1 % of |mean|, 1e-12): the std where it is larger; the floor for
    a quantized instrument (five equal readings) and for a level of exactly 0."""
    out = estimate_noise([1.0, 1.1, 0.9, 1.0, 1.0])  # squared deviations sum to 0.02, n - 1 = 4
    assert out["spread"] == pytest.approx(0.005**0.5) and out["sigma"] == out["spread"]
    assert out["mean"] == pytest.approx(1.0) and out["n"] == 5
    quantized = estimate_noise([0.52] * 5)
    assert quantized["spread"] == 0.0
    assert quantized["sigma"] == pytest.approx(NOISE_FLOOR_REL * 0.52) == quantized["floor"]
    assert estimate_noise([0.0, 0.0, 0.0])["sigma"] == NOISE_FLOOR_ABS
    assert estimate_noise([-2.0, -2.0])["sigma"] == pytest.approx(0.02)  # |mean|
    with pytest.raises(ValueError, match="at least two finite readings"):
        estimate_noise([1.0])
    with pytest.raises(ValueError, match="at least two finite readings"):
        estimate_noise([1.0, float("nan")])


def test_noise_reads_is_bounded():
    assert RunOptions(noise_reads=5).noise_reads == 5 and RunOptions().noise_reads == 0
    for bad in (1, 2, 51, 2.5, -1):
        with pytest.raises(ValueError, match="noise_reads must be 0 or an integer in"):
            RunOptions(noise_reads=bad)


def test_the_best_is_never_kept_below_the_start():
    """Maximizing, fresh readings at the best that average below the control reading at the
    start are refused (by how much is said); at or above it they are not; minimizing mirrored;
    without a control reading (the best is the start) nothing to compare."""
    conf = {"mean": 0.321, "readings": [0.3, 0.33, 0.333]}
    why = below_start(conf, {"mean": 0.522}, maximize=True)
    assert "average 0.321, below the control reading 0.522" in why and "by 0.201" in why
    assert conf["not_below_start"] is False and conf["control_mean"] == 0.522
    assert below_start({"mean": 0.522, "readings": [0.522]}, {"mean": 0.522}, True) is None
    assert below_start({"mean": 0.6, "readings": [0.6]}, {"mean": 0.522}, True) is None
    assert "above the control" in below_start({"mean": 0.6, "readings": [0.6]}, {"mean": 0.5},
                                               maximize=False)  # fmt: skip
    assert below_start({"mean": 0.4, "readings": [0.4]}, {"mean": 0.5}, False) is None
    assert below_start(conf, None, True) is None
    assert below_start(conf, {"error": "no reading"}, True) is None


def first_reads(n: int) -> list[float]:
    """The first ``n`` readings a fresh :class:`Scripted` gives at the initial knobs."""
    m = Scripted()
    return [m.read() for _ in range(n)]


@pytest.mark.parametrize("noise_reads, at", [(5, 10), (0, 4)])
def test_a_2x_glitch_without_stated_noise(tmp_path, noise_reads, at):
    """No noise stated, a single reading at twice the run's level (at evaluation 4). Measured
    from 5 readings at the initial knobs (logged in the start record, sigma = their std), the
    glitch is far from the run's own readings, read again, not repeated: discarded, never an
    evaluation nor the best. Without the measurement (noise_reads 0, the old behaviour) the
    same glitch is an evaluation and the run's best."""
    glitch = 2 * (1.0 + sum(INITIAL))
    m = Scripted(glitches={at: glitch})
    table = optimize(m, Walk(BOUNDS, step=0.05), None, 6, log=tmp_path / "r.jsonl",
                     noise_reads=noise_reads)  # fmt: skip
    log = read_log(tmp_path / "r.jsonl")
    noise = log.starts[0].get("noise")
    if noise_reads == 0:
        assert noise is None and glitch in table["y"].tolist()
        assert log.last_end["best"]["y"] == glitch
        return
    expected = estimate_noise(first_reads(5))
    assert noise["source"] == "measured" and noise["n"] == 5
    assert noise["readings"] == expected["readings"]
    assert noise["sigma"] == pytest.approx(expected["sigma"])
    assert [d["y"] for d in log.discarded] == [glitch]
    assert glitch not in table["y"].tolist() and log.last_end["best"]["y"] < 1.5 * glitch / 2


class Plateau(GuardedMachine):
    r"""Noise-free readings :math:`1 + 0.05(\sum x - 0.3)` (1.0 at the initial knobs); once
    ``ended`` (after the last evaluation) every point but the initial one reads ``drop`` less."""

    def __init__(self, drop: float):
        super().__init__(BOUNDS, ["qs1", "qs2"], x_init=list(INITIAL))
        self.drop, self.ended = drop, False

    def _apply(self, x):
        pass

    def read(self):
        y = 1.0 + 0.05 * (float(self._x.sum()) - 0.3)
        moved = not torch.equal(self._x, torch.tensor(INITIAL, dtype=D))
        return y - self.drop if self.ended and moved else y


@pytest.mark.parametrize("drop", [0.03, 0.0])
def test_restore_best_never_sets_the_knobs_below_the_start(tmp_path, drop):
    """The best (1.015) reproduces within its tolerance at the end but reads 0.985, below the
    control reading at the start (1.0): the knobs go back to the initial ones and no best is
    reported. When it still reads 1.015 the knobs stay at the best. The noise is measured (five
    equal readings: the 1 % floor, 0.01)."""
    m = Plateau(drop)

    def callback(row):
        m.ended = row["step"] == 3

    run = {"restore": "best", "noise_reads": 5, "log": tmp_path / "r.jsonl", "callback": callback}
    if drop > 0:
        with pytest.warns(UserWarning, match="the best point reads worse than the start"):
            optimize(m, Walk(BOUNDS, step=0.05), None, 4, **run)
    else:
        optimize(m, Walk(BOUNDS, step=0.05), None, 4, **run)
    log = read_log(tmp_path / "r.jsonl")
    end = log.last_end
    assert log.starts[0]["noise"]["sigma"] == pytest.approx(0.01)
    conf = end["best_confirmation"]
    assert end["control_reading"]["confirmed"] and conf["control_mean"] == pytest.approx(1.0)
    assert conf["mean"] == pytest.approx(1.015 - drop)
    if drop > 0:
        assert conf["not_below_start"] is False and conf["confirmed"] is False
        assert end["restored_to"] == "initial (best not confirmed)" and end["best"] is None
        assert m.get().tolist() == INITIAL
    else:
        assert conf["not_below_start"] is True and end["restored_to"] == "best (confirmed)"
        assert m.get().tolist() == pytest.approx(end["best"]["x"])


def test_a_resume_reuses_the_measured_noise(tmp_path):
    """A resumed run takes the noise its first start measured from the log (its start record
    says so, with that record's line) and reads the machine only for its evaluations; pigp
    report names the measurement once."""
    path = tmp_path / "r.jsonl"
    optimize(Scripted(), Walk(BOUNDS, step=0.05), None, 3, log=path, noise_reads=5)
    first = read_log(path)
    measured = first.starts[0]["noise"]
    m = Scripted()
    optimize(m, Walk(BOUNDS, step=0.05), None, 5, log=path, resume=first, noise_reads=5)
    log = read_log(path)
    assert log.starts[1]["noise"] == {"sigma": measured["sigma"], "source": "logged",
                                      "line": first.starts[0]["_line"]}  # fmt: skip
    assert m.n_reads == sum(e["reads"] for e in log.evaluations[3:])
    from pigp_torch.reporting.report import _notices

    noted = [n for n in _notices(log, log.X(), None, ["qs1", "qs2"]) if "reading noise" in n]
    assert noted == [f"reading noise {measured['sigma']:.4g} mA/min measured at the start from "
                     "5 readings at the initial setting"]  # fmt: skip
    assert SIGMA < measured["sigma"] < 3 * SIGMA or measured["sigma"] == measured["floor"]
