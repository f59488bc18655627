"""`pigp demo` says what it does as it goes: each stage's line before its work, the surrogate's
epochs, the ensemble rings and the runs with counts and seconds, on a small, fast demo."""

from __future__ import annotations

import io
import sys

import pytest

from pigp_torch.bench.demo import DemoSettings, EpochLines, run_demo


def _index(lines, start: str) -> int:
    hits = [i for i, line in enumerate(lines) if line.startswith(start)]
    assert hits, f"no line starts with {start!r}"
    return hits[0]


@pytest.fixture(scope="module")
def small_demo(tmp_path_factory):
    """The demo on one process: 5000 samples, one network, no error ensemble, 4 evaluations
    each of pigp and ml2."""
    settings = DemoSettings(n=5000, members=1, budget=4, methods=("pigp", "ml2"),
                            center_ensemble=0, no_cache=True, workers=1)  # fmt: skip
    capture = pytest.MonkeyPatch()  # the module's tests share one run (capsys is per test)
    out = io.StringIO()
    capture.setattr(sys, "stdout", out)
    try:
        table, _ = run_demo(settings)
    finally:
        capture.undo()
    return out.getvalue().splitlines(), table


def test_the_stage_lines_come_first_and_in_order_before_their_work(small_demo):
    lines, _ = small_demo
    assert lines[0].startswith("[1/4] simulated data of the model ring (error seed 0): 5000")
    s1, s2, s3, s4 = (_index(lines, f"[{k}/4]") for k in (1, 2, 3, 4))
    assert s1 < s2 < s3 < s4
    samples = _index(lines, "      5000 samples")  # stage 1's work, reported after its line
    epochs = [i for i, t in enumerate(lines) if t.startswith("      network 1/1: epoch ")]
    runs = [i for i, t in enumerate(lines) if "  evaluation " in t]
    assert s1 < samples < s2
    assert epochs and s2 < min(epochs) and max(epochs) < s3  # the training, inside stage 2
    assert len(runs) == 2 * 4 and s4 < min(runs)  # both methods run after the [4/4] line
    assert not any(line.startswith("[4/4]") for line in lines[:s4])  # one stage-4 line


def test_the_progress_lines_carry_counts_and_seconds(small_demo):
    lines, table = small_demo
    first = next(t for t in lines if t.startswith("      network 1/1: epoch "))
    assert first.startswith("      network 1/1: epoch 1/200, validation loss ")
    assert first.endswith(" s") and "(best " in first and " at epoch 1)" in first
    run = next(t for t in lines if t.startswith("           ml2  evaluation    4/4  y = "))
    assert run.endswith(" s/step") and " mA/min" in run
    assert lines[-1].startswith("      runs done (") and "the demo took " in lines[-1]
    assert sorted(table["method"].unique()) == ["ml2", "pigp"]
    assert table.groupby("method").size().tolist() == [4, 4]


def test_the_prior_check_notice_is_announced_as_expected(small_demo):
    lines, _ = small_demo
    note = lines[_index(lines, "[4/4]") + 1]
    assert "not this machine's: a NOTICE that the readings disagree with the physics prior" in note
    assert "is expected here" in note


def test_on_a_busy_machine_epoch_lines_come_every_30_s_of_wall_time(capsys):
    """0.1 s of CPU but 4 s of wall time per epoch: a line every 8 epochs (32 s)."""
    wall = [0.0]
    lines = EpochLines(1, 1, every=5.0, clock=lambda: wall[0] / 40, wall_clock=lambda: wall[0])
    for epoch in range(1, 18):
        wall[0] = 4.0 * epoch
        lines({"epoch": epoch, "max_epochs": 200, "train_loss": 1.0, "val_loss": 0.5,
               "best_val_loss": 0.5, "best_epoch": 1, "elapsed_s": wall[0]})  # fmt: skip
    out = capsys.readouterr().out.splitlines()
    assert [int(t.split("epoch ")[1].split("/")[0]) for t in out] == [1, 9, 17]


def test_an_ensemble_ring_line_has_its_number_in_the_ensemble_and_seconds(capsys):
    from pigp_torch.simulation.ensemble import ring_optima

    (result,) = ring_optima([1001], progress=True, first_index=2, total=5)
    line = capsys.readouterr().out.strip()
    assert result[0] == 1001 and result[3] is None
    assert line.startswith("ensemble ring 3/5 (seed 1001): optimum ") and " mA/min, " in line
    assert line.endswith(" s)") and float(line.rsplit("(", 1)[1].split()[0]) >= 0


def test_epoch_lines_come_every_few_cpu_seconds_and_at_the_first_and_last_epoch(capsys):
    """A line at epoch 1, then at the first epoch 5 s of CPU after the last line, and at the
    last epoch; nothing in between."""
    now = [0.0]
    lines = EpochLines(2, 3, every=5.0, clock=lambda: now[0], wall_clock=lambda: 0.0)
    for epoch in range(1, 21):
        now[0] = 0.7 * epoch  # 0.7 s of CPU per epoch
        lines({"epoch": epoch, "max_epochs": 20, "train_loss": 1.0, "val_loss": 0.5 / epoch,
               "best_val_loss": 0.5 / epoch, "best_epoch": epoch, "elapsed_s": now[0]})  # fmt: skip
    out = capsys.readouterr().out.splitlines()
    epochs = [int(t.split("epoch ")[1].split("/")[0]) for t in out]
    assert epochs == [1, 9, 17, 20]  # 0.7, 6.3 (5.6 after), 11.9 (5.6 after), the last
    assert out[0] == ("      network 2/3: epoch 1/20, validation loss 0.5 (best 0.5 at epoch 1), "
                      "1 s")  # fmt: skip
