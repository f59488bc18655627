"""Tests of the run configuration: validation messages, paths, and building each method."""

from __future__ import annotations

import json
import sys
import types

import pytest
import torch
import yaml

from pigp_torch.data.runlog import RunLog, read_log
from pigp_torch.loop.config import ConfigError
from pigp_torch.loop.run import RunSetup, build_run, check_resume, load_config, validate_config
from pigp_torch.methods import method_options
from pigp_torch.optimizers import RCDS, BayesOpt, NelderMead
from pigp_torch.optimizers.fast_bo import FastBayesOpt
from pigp_torch.optimizers.physics_bo import PhysicsModelBO
from pigp_torch.prior import PhysicsPrior

D = torch.float64
KNOBS = ["01G-QSS4", "02G-QSS3"]


def write_prior(path, names=KNOBS) -> None:
    d = len(names)
    PhysicsPrior(
        x0=torch.zeros(d, dtype=D),
        f_x0=0.9,
        f_inf=0.2,
        precision=3e4 * torch.eye(d, dtype=D),
        amplitude=0.05,
        noise=0.04,
        knob_names=list(names),
        bounds=torch.tensor([[-0.015] * d, [0.015] * d], dtype=D),
    ).save(path)


def sim(**over) -> dict:
    data = {
        "machine": {"kind": "sim", "error_seed": 1, "noise": 0.04},
        "knobs": {k: [-0.01, 0.01] for k in KNOBS},
        "method": {"name": "nelder-mead"},
        "budget": 5,
        "max_step": 0.1,
        "log": "run.jsonl",
    }
    data.update(over)
    return data


def epics(**over) -> dict:
    data = sim(
        machine={"kind": "epics", "settle_time": 0.0}, objective={"pv": "SPEAR:BeamLossRate"}
    )
    data.update(over)
    return data


@pytest.fixture
def fake_epics(monkeypatch):
    """A stand-in for pigp_torch.machine.epics that records the machines constructed."""
    made = []

    class EpicsMachine:
        def __init__(self, knob_names, bounds, objective_pv, **kwargs):
            made.append({"knob_names": knob_names, "bounds": bounds, "pv": objective_pv, **kwargs})
            self.knob_names, self.bounds = list(knob_names), bounds

    module = types.ModuleType("pigp_torch.machine.epics")
    module.EpicsMachine = EpicsMachine
    monkeypatch.setitem(sys.modules, "pigp_torch.machine.epics", module)
    return made


def test_yaml_and_json_files_load_with_paths_relative_to_the_file(tmp_path):
    """YAML and JSON give the same configuration; prior/log paths are taken from the file's
    folder; bounds and max_step come out in knob order."""
    write_prior(tmp_path / "prior.json")
    data = sim(prior="prior.json", max_step={"01G-QSS4": 0.001, "02G-QSS3": 0.002})
    (tmp_path / "run.yaml").write_text(yaml.safe_dump(data))
    (tmp_path / "run.json").write_text(json.dumps(data))
    a, b = load_config(tmp_path / "run.yaml"), load_config(tmp_path / "run.json")
    assert a.model_dump() == b.model_dump()
    assert a.log == tmp_path / "run.jsonl" and a.prior == tmp_path / "prior.json"
    assert a.bounds().tolist() == [[-0.01, -0.01], [0.01, 0.01]]
    assert a.machine_max_step().tolist() == [0.001, 0.002]
    assert a.get_prior().knob_names == KNOBS
    assert (a.restore, a.read_retries, a.objective.maximize) == ("initial", 2, True)


@pytest.mark.parametrize(
    ("data", "message"),
    [
        (sim(budgte=5), r"unknown key 'budgte' \(did you mean 'budget'\?\); allowed: machine"),
        (
            sim(machine={"kind": "sim", "nosie": 0.1}),
            r"unknown key 'machine.nosie' \(did you mean 'noise'\?\)",
        ),
        (sim(method={"name": "nelder-mead", "option": {}}), r"unknown key 'method.option'"),
        (epics(objective={"maximize": True}), r"objective.pv: the epics machine needs the obj"),
        (
            epics(machine={"kind": "epics", "setpoint_pvs": {"01G-QSS4": "A:SP"}}),
            r"machine.setpoint_pvs: no PV name for knobs \['02G-QSS3'\]",
        ),
        (
            sim(knobs={"01G-QSS4": [0.01, -0.01], "02G-QSS3": [0, 1]}),
            r"knobs: knob '01G-QSS4': lower bound 0.01 must be below upper bound -0.01",
        ),
        (sim(knobs={"01G-QSS4": [0.01, 0.01]}), r"lower bound 0.01 must be below upper"),
        (
            sim(method={"name": "nelder-mead", "options": {"size": 1}}),
            r"unknown option\(s\) \['size'",
        ),
        (sim(method={"name": "pigp"}), r"prior: method pigp needs a prior file"),
        (sim(method={"name": "pigp-fast"}), r"prior: method pigp-fast needs a prior file"),
        (
            sim(method={"name": "simplex"}),
            r"method.name: Input should be 'pigp', 'pigp-fast', 'pigp-physics', 'ml2'",
        ),
        (sim(machine={"kind": "tango"}), r"machine: Input tag 'tango'"),
        (sim(budget=0), r"budget: Input should be greater than or equal to 1"),
        (sim(objective={"pv": "X"}), r"objective.pv is for the epics machine"),
        (sim(max_step=-0.1), r"max_step must be positive"),
        ({k: v for k, v in sim().items() if k != "log"}, r"missing key 'log'"),
    ],
)
def test_each_invalid_configuration_gets_one_clear_message(data, message):
    """Wrong keys, missing PV names, empty boxes, unknown options...: one ConfigError line each."""
    with pytest.raises(ConfigError, match=message) as info:
        validate_config(data, source="run.yaml")
    assert str(info.value).startswith("run.yaml: invalid run configuration: ")
    assert "\n" not in str(info.value)


def test_several_problems_are_listed_together():
    """Every problem of a file is reported at once, one per line."""
    data = sim(budgte=5, knobs={"01G-QSS4": [1, 0]})
    with pytest.raises(ConfigError) as info:
        validate_config(data)
    lines = str(info.value).splitlines()
    assert len(lines) == 3 and "unknown key 'budgte'" in lines[1 + ("knobs" in lines[1])]


def test_a_prior_for_other_knobs_is_refused_before_any_machine(tmp_path, fake_epics):
    """A prior whose knob names differ from the run's is refused at validation: no machine is
    constructed (the fake EPICS module records none)."""
    write_prior(tmp_path / "other.json", names=["03G-QSS3", "05G-QSS3"])
    data = epics(method={"name": "pigp"}, prior="other.json")
    (tmp_path / "run.yaml").write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match=r"prior: the knobs of other.json \['03G-QSS3'"):
        load_config(tmp_path / "run.yaml")
    with pytest.raises(ConfigError, match="no such file"):
        validate_config(epics(prior=str(tmp_path / "missing.json")))
    (tmp_path / "bad.json").write_text("{}")
    with pytest.raises(ConfigError, match="not a valid PhysicsPrior file"):
        validate_config(epics(prior=str(tmp_path / "bad.json")))
    assert fake_epics == []


def test_bad_option_values_fail_before_the_machine_is_built(fake_epics):
    """Option values are checked by building the optimizer, which happens before the machine."""
    cfg = validate_config(epics(method={"name": "rcds", "options": {"step": 2.0}}))
    with pytest.raises(ConfigError, match=r"method rcds: step must lie in \(0, 1\]"):
        build_run(cfg)
    assert fake_epics == []


def test_epics_machine_gets_the_configured_pv_names_and_limits(fake_epics):
    """build_run passes PV names in knob order, the limits, and no retries of its own."""
    data = epics(
        machine={
            "kind": "epics",
            "readback_pvs": {"02G-QSS3": "B:RB", "01G-QSS4": "A:RB"},
            "tolerance": 1e-5,
            "n_average": 3,
        },
        max_step=0.2,
    )
    setup = build_run(validate_config(data))
    (made,) = fake_epics
    assert made["knob_names"] == KNOBS and made["pv"] == "SPEAR:BeamLossRate"
    assert made["readback_pvs"] == ["A:RB", "B:RB"] and made["setpoint_pvs"] is None
    assert made["setpoint_suffix"] == ":CurrSetpt" and made["readback_suffix"] == ":Curr1"
    assert made["tolerance"] == 1e-5 and made["n_average"] == 3 and made["settle_time"] == 0.5
    assert made["max_step"] == 0.2 and made["read_retries"] == 0
    assert made["bounds"].tolist() == [[-0.01, -0.01], [0.01, 0.01]]
    assert isinstance(setup.optimizer, NelderMead)


def test_each_method_is_built_with_its_options(tmp_path):
    """pigp: PI-GP BayesOpt with the benchmark defaults and the configured seed; ml2 fits on run
    data only; nelder-mead and rcds take their options; the sim machine uses the run's box."""
    write_prior(tmp_path / "p.json")
    base = {"prior": str(tmp_path / "p.json"), "log": str(tmp_path / "r.jsonl")}
    pigp = build_run(validate_config(sim(method={"name": "pigp", "seed": 7}, **base)))
    assert isinstance(pigp.optimizer, BayesOpt)
    assert (pigp.optimizer.step_limit, pigp.optimizer.beta, pigp.optimizer.seed) == (0.3, 4.0, 7)
    assert pigp.machine.bounds.tolist() == [[-0.01, -0.01], [0.01, 0.01]]
    assert pigp.machine.knob_names == KNOBS and pigp.machine.max_step.tolist() == [1e-3, 1e-3]
    ml2 = build_run(validate_config(sim(method={"name": "ml2", "options": {"beta": 1.0}}, **base)))
    opt = ml2.optimizer
    opt.tell(torch.zeros(2, dtype=D), 0.5)
    opt.tell(torch.full((2,), 0.002, dtype=D), 0.6)
    x = opt.ask()  # an ML-II fit on two points, no archive
    assert opt.beta == 1.0 and bool(((x >= -0.01) & (x <= 0.01)).all())
    nm = build_run(
        validate_config(sim(method={"name": "nelder-mead", "options": {"xatol": 0.01}}, **base))
    )
    assert isinstance(nm.optimizer, NelderMead) and nm.optimizer.xatol == 0.01
    rc = build_run(validate_config(sim(method={"name": "rcds", "options": {"noise": 0.1}}, **base)))
    assert isinstance(rc.optimizer, RCDS) and rc.optimizer.noise == 0.1
    assert {"kernel", "mean", "step_limit", "num_restarts"} <= method_options("pigp")
    assert "refit_every" in method_options("ml2") and "model" not in method_options("ml2")
    phys = build_run(
        validate_config(
            sim(method={"name": "pigp-physics", "options": {"residual_std": 0.0}}, **base)
        )
    )
    assert isinstance(phys.optimizer, PhysicsModelBO) and phys.optimizer.step_limit == 0.6
    assert phys.optimizer.model.residual_std == 0.0
    assert {"center_std", "info_every"} <= method_options("pigp-physics")
    ensemble_options = {"center_prior", "center_cov_scale", "center_floor_std", "shape_std"}
    assert ensemble_options <= method_options("pigp-physics")
    fast = build_run(
        validate_config(sim(method={"name": "pigp-fast", "options": {"beta": 1.0}}, **base))
    )
    opt = fast.optimizer
    assert isinstance(opt, FastBayesOpt)
    assert (opt.step_limit, opt.beta, opt.num_restarts) == (0.3, 1.0, 10)
    opt.tell(torch.zeros(2, dtype=D), 0.5)
    x = opt.ask()  # inside the configured box and the 0.3 trust box around the start
    assert bool((x.abs() <= 0.3 * 0.01 + 1e-15).all())
    assert {"mean", "num_restarts", "trust_center"} <= method_options("pigp-fast")
    assert "precision" not in method_options("pigp-fast")


def test_sim_bounds_outside_the_simulator_range_are_refused():
    """A box wider than the simulated knobs' range (±30 A) is an error, not a clip."""
    with pytest.raises(ConfigError, match=r"bounds outside the simulator's range"):
        build_run(validate_config(sim(knobs={"01G-QSS4": [-40.0, 10.0]})))


def test_the_machine_section_is_described_by_a_ring_spec(tmp_path):
    """A ``kind: sim`` section gives its ring as a RingSpec (SPEAR3 windings and range; a lattice
    file with the calibration in knob order and the run's unit), and the run's simulator is that
    spec's machine: same knobs, range and loss rate at a setting as ``spec.build(seed)``."""
    from pigp_torch.simulation.spec import RingSpec

    config = validate_config(sim(machine={"kind": "sim", "error_seed": 3, "knob_limit": 20.0}))
    spec = config.machine.ring_spec(config.knob_names, config.knob_unit)
    assert spec == RingSpec(optics="user", knobs=tuple(KNOBS), knob_limit=20.0)
    machine = build_run(config).machine
    ring = spec.build(3)
    assert machine.knob_names == ring.knob_names == KNOBS
    assert float(ring.bounds[1, 0]) == 20.0
    x = torch.tensor([0.004, -0.002], dtype=D)
    assert torch.equal(machine.sim.sim.loss_rate(x), ring.loss_rate(x))

    lattice = tmp_path / "ring.json"
    lattice.write_text("{}")
    section = {"kind": "sim", "lattice": str(lattice), "knob_calibration": {"B": 2.0, "A": 1.0}}
    config = validate_config(sim(machine=section, knobs={"A": [-1, 1], "B": [-1, 1]}))
    spec = config.machine.ring_spec(config.knob_names, "mA")
    assert (spec.lattice, spec.knobs, spec.knob_calibration) == (
        str(lattice),
        ("A", "B"),
        (1.0, 2.0),
    )
    assert (spec.knob_limit, spec.knob_units) == (30.0, "mA")


def test_x_init_starts_the_sim_and_is_validated():
    """machine.x_init sets the simulated knobs at the start; names and values are checked."""
    m = build_run(validate_config(sim(machine={"kind": "sim", "x_init": {"02G-QSS3": 0.004}})))
    assert m.machine.get().tolist() == [0.0, 0.004]
    with pytest.raises(ConfigError, match=r"machine.x_init: '03G-QSS3' is not a configured knob"):
        validate_config(sim(machine={"kind": "sim", "x_init": {"03G-QSS3": 0.0}}))
    with pytest.raises(ConfigError, match=r"02G-QSS3 = 0.5 lies outside"):
        validate_config(sim(machine={"kind": "sim", "x_init": {"02G-QSS3": 0.5}}))


def test_check_resume_allows_a_new_budget_only(tmp_path):
    """The logged configuration may be continued with a larger budget; another method, or a
    prior file that changed since, is refused with the reason."""
    write_prior(tmp_path / "p.json")
    cfg = validate_config(sim(prior="p.json"), base_dir=tmp_path)
    setup: RunSetup = build_run(cfg)
    RunLog.create(cfg.log, setup.header()).close()
    records = read_log(cfg.log)
    check_resume(validate_config(sim(prior="p.json", budget=50), base_dir=tmp_path), records)
    with pytest.raises(ConfigError, match=r"differs from the logged run in \['method'\]"):
        check_resume(
            validate_config(sim(prior="p.json", method={"name": "rcds"}), base_dir=tmp_path),
            records,
        )
    changed = PhysicsPrior.load(tmp_path / "p.json")
    changed.noise = 0.05
    changed.save(tmp_path / "p.json")
    with pytest.raises(ConfigError, match=r"prior .*p.json changed since the run started"):
        check_resume(cfg, records)


@pytest.mark.parametrize("name", ["run_sim.yaml", "run_epics.yaml"])
def test_the_example_run_files_are_valid(name):
    """The documented examples validate; their paths resolve next to the examples folder."""
    from pathlib import Path

    folder = Path(__file__).resolve().parents[2] / "examples"
    cfg = load_config(folder / name)
    assert cfg.log.resolve().parent == folder.parent / "runs"
    assert cfg.machine.kind == name.split("_")[1].split(".")[0]
    assert cfg.objective_floor == 0.1 and cfg.restore == "initial"
    assert cfg.warnings() == []
    if cfg.machine.kind == "epics":  # a tolerance a real (noisy) readback can meet
        assert cfg.machine.tolerance_fraction == 1e-3


# ------------------------------------------------------------------ run files trusted less
def test_a_key_given_twice_is_refused_in_yaml_and_json(tmp_path):
    """A second `max_step: 1.5` (or any repeated key, at any depth) is an error naming the key
    and both lines, not a silent override; JSON alike."""
    text = yaml.safe_dump(sim()) + "max_step: 1.5\n"
    (tmp_path / "run.yaml").write_text(text)
    with pytest.raises(ConfigError, match=r"duplicate key 'max_step' \(line \d+, first given"):
        load_config(tmp_path / "run.yaml")
    nested = "machine:\n  kind: sim\n  noise: 0.04\n  noise: 0.4\n"
    (tmp_path / "n.yaml").write_text(
        nested + yaml.safe_dump({k: v for k, v in sim().items() if k != "machine"})
    )
    with pytest.raises(ConfigError, match=r"duplicate key 'noise'"):
        load_config(tmp_path / "n.yaml")
    body = json.dumps(sim())[:-1] + ', "budget": 500}'
    (tmp_path / "run.json").write_text(body)
    with pytest.raises(ConfigError, match=r"duplicate key 'budget'"):
        load_config(tmp_path / "run.json")


@pytest.mark.parametrize(
    ("value", "message"),
    [
        ("missing", r"missing key 'max_step' \(a fraction .* unlimited"),
        (None, r"max_step: null is not a step limit.*write unlimited"),
        ("none", r"'none' is not a step limit"),
    ],
)
def test_max_step_must_be_given_explicitly(value, message):
    """No default step limit: a missing max_step, null or a casual 'none' are refused with the
    spellings that are accepted."""
    data = sim()
    if value == "missing":
        del data["max_step"]
    else:
        data["max_step"] = value
    with pytest.raises(ConfigError, match=message):
        validate_config(data)


def test_unlimited_and_large_step_limits_are_named_in_warnings():
    """'unlimited' is the deliberate way to run without a limit (and is warned about); a limit
    above 10 % of a knob's range is named with its share; 0.1 of the half-range is quiet."""
    assert validate_config(sim()).warnings() == []
    cfg = validate_config(sim(max_step="unlimited"))
    assert cfg.machine_max_step() is None and "no step limit" in cfg.warnings()[0]
    (line,) = validate_config(sim(max_step=0.5)).warnings()
    assert "01G-QSS4 0.005 (25 %)" in line and "02G-QSS3" in line
    (line,) = validate_config(sim(max_step={"01G-QSS4": 0.001, "02G-QSS3": 0.005})).warnings()
    assert "02G-QSS3" in line and "01G-QSS4" not in line


def test_a_logged_configuration_is_verified_against_its_digest(tmp_path):
    """The header stores the configuration's sha256; logged_config accepts it as written and
    refuses an edited header (a doubled step limit) or one without a digest — a second check
    behind the hash chain, which read_log applies first (verify=False reads past it here)."""
    from pigp_torch.loop.run import logged_config

    cfg = validate_config(sim(), base_dir=tmp_path)
    RunLog.create(cfg.log, build_run(cfg).header()).close()
    assert logged_config(read_log(cfg.log)).max_step == 0.1
    lines = cfg.log.read_text().splitlines()
    header = json.loads(lines[0])
    header["config"]["max_step"] = 0.2
    cfg.log.write_text(json.dumps(header) + "\n")
    with pytest.raises(ValueError, match=r"run.jsonl:1: the record does not match"):
        read_log(cfg.log)
    with pytest.raises(ConfigError, match="does not match its sha256"):
        logged_config(read_log(cfg.log, verify=False))
    del header["config_sha256"]
    cfg.log.write_text(json.dumps(header) + "\n")
    with pytest.raises(ConfigError, match="no configuration digest"):
        logged_config(read_log(cfg.log, verify=False))


def test_tolerance_fraction_and_stale_timeout_reach_the_epics_machine(fake_epics):
    """tolerance_fraction is a share of each knob's range; it excludes tolerance."""
    cfg = validate_config(
        epics(machine={"kind": "epics", "tolerance_fraction": 0.01, "stale_timeout": 3.0})
    )
    build_run(cfg)
    made = fake_epics[-1]
    assert made["tolerance"].tolist() == pytest.approx([2e-4, 2e-4])
    assert made["stale_timeout"] == 3.0
    with pytest.raises(ConfigError, match="not both"):
        validate_config(
            epics(machine={"kind": "epics", "tolerance": 1.0, "tolerance_fraction": 0.01})
        )


def test_a_log_written_before_the_new_keys_still_resumes_with_its_run_file(tmp_path):
    """A logged configuration without the keys added since (restore_attempts, lock_dir, ...)
    matches the run file that has their defaults; a changed safety key is still refused."""
    cfg = validate_config(sim(), base_dir=tmp_path)
    header = build_run(cfg).header()
    for key in ("restore_attempts", "restore_interval", "lock_dir"):
        del header["config"][key]
    RunLog.create(cfg.log, header).close()
    check_resume(cfg, read_log(cfg.log))
    with pytest.raises(ConfigError, match=r"differs from the logged run in \['restore_attempts'\]"):
        check_resume(validate_config(sim(restore_attempts=5), base_dir=tmp_path), read_log(cfg.log))


@pytest.mark.parametrize(
    ("value", "message"),
    [(-1.0, "greater than or equal to 0"), (4000.0, "less than or equal to 3600"),
     (float("nan"), "restore_timeout"), (float("inf"), "restore_timeout"), ("30", "number")],
)  # fmt: skip
def test_restore_timeout_is_validated(tmp_path, value, message):
    """restore_timeout: seconds, default 30, from 0 to 3600, a number (not a string)."""
    assert validate_config(sim(), base_dir=tmp_path).restore_timeout == 30.0
    assert validate_config(sim(restore_timeout=0), base_dir=tmp_path).restore_timeout == 0.0
    with pytest.raises(ConfigError, match=message):
        validate_config(sim(restore_timeout=value), base_dir=tmp_path)
    setup = build_run(validate_config(sim(restore_timeout=12.5), base_dir=tmp_path))
    assert setup.options().restore_timeout == 12.5
