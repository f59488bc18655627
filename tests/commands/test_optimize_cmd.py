"""Tests of `pigp optimize`: a run on the simulated machine, dry run, resume, bad input, and the
knobs restored when the process is stopped by SIGINT or SIGTERM."""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import time

import pytest
import yaml

from pigp_torch import cli
from pigp_torch.commands.optimize import register
from pigp_torch.data.runlog import read_log

KNOBS = ["01G-QSS4", "02G-QSS3"]
X_INIT = {"01G-QSS4": 0.002, "02G-QSS3": -0.001}


@pytest.fixture(autouse=True)
def with_optimize_command(monkeypatch):
    """`pigp optimize` registered the way cli.py does it (COMMAND_MODULES)."""
    modules = tuple(dict.fromkeys((*cli.COMMAND_MODULES, "optimize")))
    monkeypatch.setattr(cli, "COMMAND_MODULES", modules)


def write_config(tmp_path, name="run.yaml", **over) -> str:
    data = {
        "machine": {"kind": "sim", "error_seed": 1, "noise": 0.04, "seed": 2, "x_init": X_INIT},
        "knobs": {k: [-0.01, 0.01] for k in KNOBS},
        "method": {"name": "nelder-mead", "options": {"initial_simplex_size": 0.2}},
        "budget": 5,
        "max_step": 0.1,
        "log": "run.jsonl",
    }
    data.update(over)
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data))
    return str(path)


def test_register_adds_a_documented_command(capsys):
    """register() adds `optimize` with its options to a fresh parser."""
    parser = argparse.ArgumentParser(prog="pigp")
    register(parser.add_subparsers(dest="command"), None)
    with pytest.raises(SystemExit):
        parser.parse_args(["optimize", "--help"])
    text = capsys.readouterr().out
    for option in ("--config", "--resume", "--dry-run", "--quiet"):
        assert option in text
    args = parser.parse_args(["optimize", "--config", "r.yaml", "--dry-run"])
    assert args.dry_run and str(args.config) == "r.yaml" and args.resume is None


def test_a_run_prints_steps_and_a_summary_and_restores_the_knobs(tmp_path, capsys):
    """5 evaluations: a line per step, the summary (best y and where, the restore), exit 0, and
    a log whose end record has the initial knobs as readback."""
    assert cli.main(["optimize", "--config", write_config(tmp_path)]) == 0
    out = capsys.readouterr().out
    log = read_log(tmp_path / "run.jsonl")
    steps = [line for line in out.splitlines() if line.startswith("evaluation ")]
    assert log.n_evaluations == 5 and len(steps) == 5
    assert steps[0].startswith("evaluation    1/5") and steps[-1].startswith("evaluation    5/5")
    step, _, y = log.best()
    assert f"best y = {y:.6g} mA/min at evaluation {step + 1}" in out
    # units on every number: readings in mA/min, knob moves and settings in A
    assert " mA/min  best = " in steps[1] and " A (0" in steps[1]
    assert "readback: 01G-QSS4=0.002, 02G-QSS3=-0.001 (A)" in out
    assert "status: completed" in out and "knobs restored to initial" in out
    assert log.last_end["final_knobs"] == list(X_INIT.values()) == log.starts[0]["initial_knobs"]
    assert log.header["config"]["budget"] == 5 and log.header["knob_names"] == KNOBS


def test_dry_run_prints_the_plan_and_touches_nothing(tmp_path, capsys):
    """--dry-run shows the knobs, their limits and current values and writes no log."""
    assert cli.main(["optimize", "--config", write_config(tmp_path), "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert "plan: nelder-mead on the simulated ring" in out and "dry run" in out
    assert "01G-QSS4" in out and "0.002" in out and "0.001" in out  # now / max step columns
    assert "lower (A)" in out and "max step (A)" in out and "noise 0.04 mA/min" in out
    assert not (tmp_path / "run.jsonl").exists()


def test_resume_extends_a_run_like_a_longer_run(tmp_path, capsys):
    """4 evaluations, then --resume with budget 9: the log equals an uninterrupted 9-run's."""
    one = write_config(tmp_path, "a.yaml", budget=9, log="a.jsonl")
    assert cli.main(["optimize", "--config", one, "--quiet"]) == 0
    short = write_config(tmp_path, "b.yaml", budget=4, log="b.jsonl")
    assert cli.main(["optimize", "--config", short, "--quiet"]) == 0
    longer = write_config(tmp_path, "b9.yaml", budget=9, log="b.jsonl")
    argv = ["optimize", "--config", longer, "--resume", str(tmp_path / "b.jsonl"), "--quiet"]
    assert cli.main(argv) == 0
    assert "continue at step 4" in capsys.readouterr().out
    a, b = read_log(tmp_path / "a.jsonl"), read_log(tmp_path / "b.jsonl")
    assert b.n_evaluations == 9
    assert b.X().tolist() == a.X().tolist() and b.Y().tolist() == a.Y().tolist()
    assert cli.main(["optimize", "--resume", str(tmp_path / "b.jsonl")]) == 2  # budget reached
    assert "already holds 9 evaluations" in capsys.readouterr().err


def test_bad_input_exits_2_with_one_message(tmp_path, capsys):
    """An invalid run file, an existing log, or nothing to run: exit 2 and a clear message."""
    assert cli.main(["optimize", "--config", write_config(tmp_path, budgte=3)]) == 2
    assert "unknown key 'budgte' (did you mean 'budget'?)" in capsys.readouterr().err
    (tmp_path / "run.jsonl").write_text("")
    assert cli.main(["optimize", "--config", write_config(tmp_path)]) == 2
    assert "exists: continue it with --resume" in capsys.readouterr().err
    assert cli.main(["optimize"]) == 2
    assert "give a run file with --config" in capsys.readouterr().err


def test_objective_floor_abort_exits_1(tmp_path, capsys):
    """A reading below objective_floor: exit 1, status aborted, knobs restored."""
    assert cli.main(["optimize", "--config", write_config(tmp_path, objective_floor=5.0)]) == 1
    captured = capsys.readouterr()
    assert "run aborted: RunAborted" in captured.err and "status: aborted" in captured.out
    end = read_log(tmp_path / "run.jsonl").last_end
    assert end["final_knobs"] == list(X_INIT.values()) and end["n_evaluations"] == 1


# A child process with an interactive-terminal SIGINT (a background shell starts children with
# SIGINT ignored) and `optimize` registered as cli.py will register it.
CHILD = (
    "import signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
    "signal.signal(signal.SIGHUP, signal.SIG_DFL); "
    "import pigp_torch.cli as c; "
    "c.COMMAND_MODULES = tuple(dict.fromkeys((*c.COMMAND_MODULES, 'optimize'))); "
    "sys.exit(c.main(sys.argv[1:]))"
)


@pytest.mark.parametrize(
    ("signum", "code"),
    [
        (signal.SIGINT, 130),
        pytest.param(signal.SIGTERM, 143, marks=pytest.mark.slow),
        (signal.SIGHUP, 129),
    ],
    ids=["SIGINT", "SIGTERM", "SIGHUP"],
)
def test_a_signal_stops_the_process_and_the_knobs_are_restored(tmp_path, signum, code):
    """SIGINT / SIGTERM / SIGHUP (terminal closed) after a few logged evaluations: the process
    exits promptly with 130 / 143 / 129, the log ends 'interrupted' and the final readback
    equals the initial knobs."""
    config = write_config(tmp_path, budget=100_000)
    log_path = tmp_path / "run.jsonl"
    env = {
        **os.environ,
        "OMP_NUM_THREADS": "1",
        "OPENBLAS_NUM_THREADS": "1",
        "MKL_NUM_THREADS": "1",
    }
    with open(tmp_path / "out.txt", "w") as out, open(tmp_path / "err.txt", "w") as err:
        proc = subprocess.Popen(
            [sys.executable, "-c", CHILD, "optimize", "--config", config, "--quiet"],
            stdout=out,
            stderr=err,
            env=env,
        )
        try:
            deadline = time.monotonic() + 120
            while time.monotonic() < deadline and proc.poll() is None:
                if log_path.exists() and log_path.read_text().count('"type":"evaluation"') >= 3:
                    break
                time.sleep(0.1)
            assert proc.poll() is None, (tmp_path / "err.txt").read_text()
            sent = time.monotonic()
            proc.send_signal(signum)
            rc = proc.wait(timeout=30)
            elapsed = time.monotonic() - sent
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait(timeout=10)
    assert rc == code, (tmp_path / "err.txt").read_text()
    assert elapsed < 10
    log = read_log(log_path)
    end = log.last_end
    assert end["status"] == "interrupted" and end["restored_to"] == "initial"
    assert end["final_knobs"] == list(X_INIT.values()) == log.starts[0]["initial_knobs"]
    assert log.n_evaluations >= 3 and end["n_evaluations"] == log.n_evaluations
    assert log.X()[-1].tolist() != end["final_knobs"]
    assert "status: interrupted" in (tmp_path / "out.txt").read_text()


@pytest.mark.slow
def test_a_run_over_channel_access_against_the_simulated_ioc(tmp_path, capsys):
    """`pigp optimize` on an EpicsMachine talking to the simulated IOC over CA (127.0.0.1):
    the dry run moves nothing; the run logs every evaluation and the IOC's knobs end where
    they were found."""
    import torch

    from pigp_torch.machine.epics import EpicsMachine
    from pigp_torch.simulated_epics.ioc import start_sim_ioc

    start = torch.tensor(list(X_INIT.values()), dtype=torch.float64)
    bounds = torch.tensor([[-0.01, -0.01], [0.01, 0.01]], dtype=torch.float64)
    with start_sim_ioc(1, knobs=KNOBS, update_period=0.05) as ioc:
        with EpicsMachine(KNOBS, bounds, ioc.loss_rate_pv, settle_time=0.1) as m:
            m.set(start)
        machine = {"kind": "epics", "settle_time": 0.1, "timeout": 1.0}
        config = write_config(
            tmp_path, machine=machine, objective={"pv": ioc.loss_rate_pv}, retry_interval=0.05
        )
        assert cli.main(["optimize", "--config", config, "--dry-run"]) == 0
        assert "plan: nelder-mead on the EPICS" in capsys.readouterr().out
        assert not (tmp_path / "run.jsonl").exists()
        assert cli.main(["optimize", "--config", config, "--quiet"]) == 0
        with EpicsMachine(KNOBS, bounds, ioc.loss_rate_pv) as m:
            after = m.get()
    log = read_log(tmp_path / "run.jsonl")
    assert log.n_evaluations == 5 and log.last_end["status"] == "completed"
    assert torch.allclose(after, start, rtol=0, atol=1e-8)
    assert log.starts[0]["initial_knobs"] == pytest.approx(start.tolist(), abs=1e-8)
    assert log.last_end["final_knobs"] == pytest.approx(start.tolist(), abs=1e-8)
    assert len(set(map(tuple, log.X().tolist()))) == 5  # five different settings were measured


def test_help_lists_every_method_and_the_exit_codes(capsys):
    """`pigp optimize --help` names every method of the run files and documents each exit
    status, the one for knobs NOT restored and the one for a refused lock included."""
    from pigp_torch.methods import run_file_methods

    with pytest.raises(SystemExit):
        cli.main(["optimize", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    for name in run_file_methods():
        assert name in text
    assert "3 the knobs were NOT restored" in text and "4 refused: another run holds" in text
    assert "129 stopped by SIGHUP" in text


def test_dry_run_checks_the_log_path_and_prints_warnings(tmp_path, capsys):
    """--dry-run is not refused when the log exists (it writes nothing) but says so and what a
    run would do; it refuses a log folder it cannot write, and prints the step-limit
    warnings."""
    (tmp_path / "run.jsonl").write_text("")
    assert cli.main(["optimize", "--config", write_config(tmp_path), "--dry-run"]) == 0
    captured = capsys.readouterr()
    assert "exists: continue it with --resume" in captured.err
    assert "a run with this file would be refused (exit 2)" in captured.err
    assert "not a run log that can be continued" in captured.err  # an empty file
    assert "plan: nelder-mead" in captured.out and "dry run: nothing was moved" in captured.out
    assert (tmp_path / "run.jsonl").read_text() == ""
    config = write_config(tmp_path, "big.yaml", log="big.jsonl", max_step=0.5)
    assert cli.main(["optimize", "--config", config, "--dry-run"]) == 0
    assert "warning: max_step above 10 % of the knob's range" in capsys.readouterr().err
    (tmp_path / "file").write_text("")  # a folder that cannot exist: a file is in the way
    config = write_config(tmp_path, "bad.yaml", log="file/sub/run.jsonl")
    assert cli.main(["optimize", "--config", config, "--dry-run"]) == 2
    assert "cannot be created" in capsys.readouterr().err


def test_resume_without_config_prints_the_verified_safety_limits(tmp_path, capsys):
    """--resume LOG alone: the header's configuration is verified against its sha256 and its
    safety limits are printed; an edited header (a doubled step limit) exits 2 (the hash chain
    names line 1)."""
    short = write_config(tmp_path, "b.yaml", budget=5, log="b.jsonl")
    assert cli.main(["optimize", "--config", short, "--quiet"]) == 0
    log = tmp_path / "b.jsonl"
    lines = log.read_text().splitlines(keepends=True)  # as if killed after 3 evaluations
    third = [k for k, line in enumerate(lines) if '"type":"evaluation"' in line][2]
    log.write_text("".join(lines[: third + 1]))
    assert cli.main(["optimize", "--resume", str(log), "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert "sha256 verified" in out and "max_step: 0.1" in out
    lines = log.read_text().splitlines(keepends=True)
    lines[0] = lines[0].replace('"max_step":0.1', '"max_step":0.2')
    log.write_text("".join(lines))
    assert cli.main(["optimize", "--resume", str(log), "--dry-run"]) == 2
    assert "b.jsonl:1: the record does not match the log's hash chain" in capsys.readouterr().err


def test_units_from_the_run_file_are_printed(tmp_path, capsys):
    """objective_unit / knob_unit of the run file replace the defaults in the plan, the progress
    lines and the summary."""
    path = write_config(tmp_path, objective_unit="counts/s", knob_unit="mrad")
    assert cli.main(["optimize", "--config", path]) == 0
    out = capsys.readouterr().out
    assert "lower (mrad)" in out and "noise 0.04 counts/s" in out
    steps = [line for line in out.splitlines() if line.startswith("evaluation ")]
    assert " counts/s  best = " in steps[2] and " mrad (" in steps[2]
    assert "mA/min" not in out and "(A)" not in out and "(mrad)" in out
    assert read_log(tmp_path / "run.jsonl").header["config"]["knob_unit"] == "mrad"


def test_any_ring_from_a_lattice_file(tmp_path, capsys):
    """machine.lattice: the SPEAR3 design deck as a user's file with three knobs by element name
    (calibration per knob); the readings are that ring's loss rate (its error seed 2) plus noise,
    and a lattice without calibration or an unknown element is refused with exit 2."""
    import shutil

    import torch

    from pigp_torch.simulation import RingCoupling
    from pigp_torch.simulation.deck import deck_path

    shutil.copy(deck_path("design"), tmp_path / "ring.json")
    knobs = ["01G-QSS4", "02G-QSS3", "05G-QSS3"]
    machine = {"kind": "sim", "error_seed": 2, "noise": 0.0, "lattice": "ring.json",
               "knob_calibration": dict.fromkeys(knobs, 5.15e-4)}  # fmt: skip
    over = {"machine": machine, "knobs": {k: [-20, 20] for k in knobs}, "budget": 6}
    assert cli.main(["optimize", "--config", write_config(tmp_path, **over)]) == 0
    out = capsys.readouterr().out
    assert "lattice " in out and "ring.json" in out
    log = read_log(tmp_path / "run.jsonl")
    assert log.n_evaluations == 6 and log.last_end["status"] == "completed"
    ring = RingCoupling(tmp_path / "ring.json", knobs, 5.15e-4, error_seed=2)
    torch.testing.assert_close(log.Y(), ring.loss_rate(log.X()), rtol=1e-9, atol=1e-12)
    assert float(log.Y()[0]) != float(RingCoupling(tmp_path / "ring.json", knobs, 5.15e-4)
                                      .loss_rate(log.X()[0]))  # seed 2, not seed 1  # fmt: skip
    bad = dict(machine, knob_calibration=None)
    path = write_config(tmp_path, "b.yaml", log="b.jsonl", **dict(over, machine=bad))
    assert cli.main(["optimize", "--config", path]) == 2
    assert "knob_calibration" in capsys.readouterr().err
    wrong = {"NOPE": [-1, 1], **over["knobs"]}
    path = write_config(tmp_path, "c.yaml", log="c.jsonl", **dict(over, knobs=wrong))
    assert cli.main(["optimize", "--config", path]) == 2
    assert "NOPE" in capsys.readouterr().err


def test_loss_map_benchmark_is_the_demos_machine(tmp_path, capsys):
    """machine.loss_map: benchmark runs the benchmark's (and pigp demo's) machine of that seed:
    the same noise-free loss rates as the protocol's machine, not those of SPEAR3's own map."""
    import torch

    from pigp_torch.bench.protocol import benchmark_ring
    from pigp_torch.simulation import Spear3Coupling
    from pigp_torch.simulation.spec import RingSpec

    machine = {"kind": "sim", "error_seed": 1, "noise": 0.0, "loss_map": "benchmark"}
    assert cli.main(["optimize", "--config", write_config(tmp_path, machine=machine)]) == 0
    assert "error seed 1 with the benchmark's loss-rate map" in capsys.readouterr().out
    log = read_log(tmp_path / "run.jsonl")
    bench = benchmark_ring(1, RingSpec(knobs=tuple(KNOBS)), True)
    torch.testing.assert_close(log.Y(), bench.loss_rate(log.X()), rtol=1e-9, atol=1e-12)
    own = Spear3Coupling(1, knobs=KNOBS).loss_rate(log.X())
    assert float((log.Y() - own).abs().min()) > 1e-3  # another machine than SPEAR3's map gives
