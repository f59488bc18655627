"""`pigp optimize` on the simulated ARES-EA linac (machine kind: ares-sim): the online loop with
the screen's four beam numbers logged and told, resume, report and the run file's checks.

Trials 0-49 only (the tuning trials of the ARES protocol)."""

from __future__ import annotations

import pytest
import torch
import yaml

from pigp_torch import cli
from pigp_torch.data.runlog import read_log
from pigp_torch.loop.config import ConfigError
from pigp_torch.loop.run import build_machine, load_config, validate_config
from pigp_torch.machines.ares_ea.simulation import KNOB_NAMES, KNOB_UNITS, knob_bounds
from pigp_torch.reporting.dashboard import run_state

LIMITS = knob_bounds()
KNOBS = {n: [float(LIMITS[0, i]), float(LIMITS[1, i])] for i, n in enumerate(KNOB_NAMES)}
UM = 1e-6


@pytest.fixture(autouse=True)
def with_optimize_command(monkeypatch):
    """`pigp optimize` and `pigp report` registered the way cli.py does it."""
    modules = tuple(dict.fromkeys((*cli.COMMAND_MODULES, "optimize", "report")))
    monkeypatch.setattr(cli, "COMMAND_MODULES", modules)


def run_file(tmp_path, name="run.yaml", machine=None, **over) -> str:
    data = {
        "machine": {"kind": "ares-sim", "trial": 3, **(machine or {})},
        "knobs": KNOBS,
        "method": {"name": "ares-physics"},
        "budget": 8,
        "max_step": 0.5,
        "log": name.replace(".yaml", ".jsonl"),
    }
    data.update(over)
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return str(path)


def noise_free_beam(path: str, X: torch.Tensor) -> torch.Tensor:
    """The machine's noise-free beam (m) at the logged settings, from the run file."""
    return build_machine(load_config(path)).true_observables(X)


def test_ares_physics_runs_online_and_logs_the_beam(tmp_path, capsys):
    """ares-physics, 8 evaluations with ramped moves: every reading logs the four beam numbers,
    equal to the machine's noise-free beam at the logged setting, the objective is their MAE
    to the target (minimized, in m), and the best reading is within 40 um of the target."""
    path = run_file(tmp_path)
    assert cli.main(["optimize", "--config", path, "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "simulated ARES-EA linac (trial 3" in out
    plan = [line.split() for line in out.splitlines() if line.strip().startswith("AREAM")]
    assert [row[-1] for row in plan] == list(KNOB_UNITS)  # the plan gives each knob its unit
    log = read_log(tmp_path / "run.jsonl")
    assert log.header["knob_units"] == list(KNOB_UNITS)
    assert log.n_evaluations == 8 and log.last_end["status"] == "completed"
    assert log.observable_names == ["mu_x", "sigma_x", "mu_y", "sigma_y"]
    assert log.observable_units == ["m"] * 4
    assert log.header["maximize"] is False and log.header["config"]["objective_unit"] == "m"
    obs = log.observables()
    assert obs is not None and obs.shape == (8, 4)
    assert torch.equal(obs, noise_free_beam(path, log.X()))
    machine = build_machine(load_config(path))
    assert torch.allclose(log.Y(), machine.mae(obs), rtol=1e-12, atol=0)
    assert float(log.Y().min()) < 40 * UM
    assert float(log.Y()[0]) > 100 * UM  # the start is far off: the run did the tuning
    assert len(log.intents) > 8  # some moves were ramped (max_step 0.5 of the half-range)
    assert log.last_end["final_knobs"] == pytest.approx([10.0, -10.0, 0.0, 10.0, 0.0])
    # a person reads the beam in µm (the log keeps m) and each knob with its own unit
    best = log.last_end["best"]
    assert f"best y = {1e6 * best['y']:.6g} µm at evaluation {best['step'] + 1}: " in out
    assert f"AREAMQZM1={best['x'][0]:.6g} 1/m^2, " in out
    assert f"AREAMCHM1={best['x'][4]:.6g} rad" in out and "minimize the objective (µm)" in out


def test_published_nm_runs_online_and_logs_the_beam(tmp_path):
    """published-nm, 10 evaluations: its objective is the beam distance (MAE, 100x off the
    screen), minimized without maximize in the run file; the beam is logged with every reading
    and equals the noise-free beam; restore: best leaves the knobs at the best reading; the
    report names the best reading's beam with units and the dashboard reads the log."""
    path = run_file(
        tmp_path,
        machine={"trial": 0},
        method={"name": "published-nm"},
        budget=10,
        max_step="unlimited",
        restore="best",
    )
    assert cli.main(["optimize", "--config", path, "--quiet"]) == 0
    log = read_log(tmp_path / "run.jsonl")
    assert log.n_evaluations == 10 and log.header["maximize"] is False
    i = int(log.Y().argmin())
    assert i > 0  # the simplex found a better setting than the start
    assert log.last_end["restored_to"] == "best (confirmed)"  # fresh readings agreed
    assert log.last_end["final_knobs"] == log.X()[i].tolist()
    obs = log.observables()
    assert torch.equal(obs, noise_free_beam(path, log.X()))
    machine = build_machine(load_config(path))
    assert machine.objective == "distance"
    assert torch.allclose(log.Y(), machine.objective_of(obs), rtol=1e-12, atol=0)
    assert len({tuple(x) for x in log.X().tolist()}) > 5  # the simplex moved
    assert cli.main(["report", str(tmp_path / "run.jsonl")]) == 0
    page = (tmp_path / "run_report.html").read_text()
    assert f"mu_x = {1e6 * float(obs[i, 0]):.6g} µm" in page  # the beam in µm for a person
    assert f"sigma_y = {1e6 * float(obs[i, 3]):.6g} µm" in page
    assert f"best reading {1e6 * float(log.Y()[i]):.6g} µm at evaluation {i + 1}" in page
    assert "AREAMCVM1 in rad" in page and "AREAMQZM1 in 1/m^2" in page
    state = run_state(tmp_path / "run.jsonl")  # the dashboard's page reads the same log
    assert state["n"] == 10 and state["objective_unit"] == "µm"  # shown in µm, logged in m
    assert state["best_y"] == pytest.approx(1e6 * float(log.Y()[i]), rel=1e-12)


@pytest.mark.slow
def test_a_resumed_ares_run_retells_the_beam(tmp_path, capsys):
    """ares-physics with screen noise: 3 evaluations, then --resume to 7, logs the same
    settings, readings and beam as an uninterrupted 7-run (the resumed optimizer was told the
    logged beam and its fit asks the same points; the noise stream was moved on)."""
    noisy = {"noise": 5 * UM, "seed": 4}
    full = run_file(tmp_path, "a.yaml", machine=noisy, budget=7)
    assert cli.main(["optimize", "--config", full, "--quiet"]) == 0
    short = run_file(tmp_path, "b.yaml", machine=noisy, budget=3)
    assert cli.main(["optimize", "--config", short, "--quiet"]) == 0
    longer = run_file(tmp_path, "b7.yaml", machine=noisy, budget=7, log="b.jsonl")
    argv = ["optimize", "--config", longer, "--resume", str(tmp_path / "b.jsonl"), "--quiet"]
    assert cli.main(argv) == 0
    assert "continue at step 3" in capsys.readouterr().out
    a, b = read_log(tmp_path / "a.jsonl"), read_log(tmp_path / "b.jsonl")
    assert b.n_evaluations == 7 and len(b.starts) == 2
    assert b.X().tolist() == a.X().tolist() and b.Y().tolist() == a.Y().tolist()
    assert b.observables().tolist() == a.observables().tolist()
    beam = noise_free_beam(full, a.X())
    assert 0 < float((a.observables() - beam).abs().max()) < 10 * 5 * UM  # noisy, as stated


def test_replay_needs_the_logged_beam(tmp_path):
    """An ARES log whose evaluations lack the beam cannot rebuild ares-physics (it fits the
    beam): the replay says so; the same records with the beam replay."""
    from pigp_torch.data.runlog import ReplayError, replay
    from pigp_torch.loop.run import build_optimizer

    path = run_file(tmp_path, budget=2)
    assert cli.main(["optimize", "--config", path, "--quiet"]) == 0
    log, config = read_log(tmp_path / "run.jsonl"), load_config(path)
    assert replay(build_optimizer(config), log) == 2
    bare = [{k: v for k, v in r.items() if k != "observables"} for r in log.evaluations]
    with pytest.raises(ReplayError, match="needs the observables"):
        replay(build_optimizer(config), bare)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"knobs": {**{n: v for n, v in KNOBS.items() if n != "AREAMCHM1"}, "Q4": [-1, 1]}},
         "an ares-sim run has the five ARES knobs"),
        ({"knobs": {**KNOBS, "AREAMQZM1": [-80.0, 72.0]}},
         "knobs: bounds outside the magnets' ranges AREAMQZM1 [-72, 72] 1/m^2"),
        ({"machine": {"trial": 4000}}, "machine.trial: no trial 4000 in the shipped trials"),
        ({"machine": {"model_error": "quad-cal-20"}},
         "machine.model_error: unknown model-error case 'quad-cal-20'"),
        ({"objective": {"maximize": True}},
         "objective.maximize: ares-physics reads the ARES objective 'mae', which is minimized"),
        ({"objective_unit": "mA/min"}, "objective_unit: the ARES objective 'mae' is in 'm'"),
        ({"machine": {"trials": "missing.yaml"}}, "machine.trials: trials file not found"),
        ({"machine": {"noies": 1e-6}},
         "unknown key 'machine.noies' (did you mean 'noise'?); allowed: kind, trial, trials"),
        ({"machine": {"noise": -1e-6}}, "machine.noise: Input should be greater than or equal"),
        ({"machine": {"kind": "sim"}, "knobs": {"01G-QSS4": [-1.0, 1.0]}},
         "ares-physics is a method of the ARES-EA linac; it runs on machine kind: ares-sim"),
    ],
)  # fmt: skip
def test_config_errors_are_one_clear_line(tmp_path, change, message):
    """Wrong knobs, bounds outside the magnets' ranges, an unknown trial or case, a direction or
    unit against the method's objective, an ARES method on another machine: one ConfigError
    line naming the key."""
    data = yaml.safe_load(open(run_file(tmp_path)).read())
    for key, value in change.items():
        data[key] = {**data[key], **value} if key == "machine" else value
    if data["machine"]["kind"] == "sim":
        data["machine"] = {"kind": "sim"}
    with pytest.raises(ConfigError) as err:
        validate_config(data, base_dir=tmp_path, source="run.yaml")
    text = str(err.value)
    assert "\n" not in text and text.startswith("run.yaml: invalid run configuration: ")
    assert message in text


def test_defaults_follow_the_method(tmp_path):
    """Left out, maximize and the units follow the method's objective: published-bo maximizes
    the dimensionless reward; the machine starts at x_init by name, else the published start."""
    data = yaml.safe_load(open(run_file(tmp_path, method={"name": "published-bo"})).read())
    data["machine"]["x_init"] = {"AREAMQZM2": -5.0}
    config = validate_config(data, base_dir=tmp_path)
    assert config.objective.maximize is True and config.objective_unit == "1"
    assert config.knob_unit == "1/m^2 or rad"
    machine = build_machine(config)
    assert machine.objective == "reward" and machine.get().tolist() == [10, -5, 0, 10, 0]
    assert torch.equal(machine.bounds, config.bounds())


def test_the_example_runs_as_documented(tmp_path):
    """examples/run_ares_ea.yaml validates (no warnings, its log next to the examples folder) and
    runs as is (only its log moved here): every reading logs the beam, and the run ends within
    40 um of the target."""
    from pathlib import Path

    example = Path(__file__).resolve().parents[2] / "examples" / "run_ares_ea.yaml"
    config = load_config(example)
    assert config.log.resolve().parent == example.parent.parent / "runs"
    assert config.warnings() == [] and config.machine.trial < 50
    data = yaml.safe_load(example.read_text())
    data["log"] = str(tmp_path / "run.jsonl")
    (tmp_path / "run.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    assert cli.main(["optimize", "--config", str(tmp_path / "run.yaml"), "--quiet"]) == 0
    log = read_log(tmp_path / "run.jsonl")
    assert log.n_evaluations == config.budget and log.observables().shape == (config.budget, 4)
    assert float(log.Y().min()) < 40 * UM
