"""The run file's reading options reach the loop: objective_range, and the stated noise of one
reading (objective_noise, else the simulated machine's noise, else the prior's)."""

from __future__ import annotations

import pytest
import yaml

from pigp_torch.loop.config import ConfigError
from pigp_torch.loop.run import RunSetup, load_config
from tests.run.test_run_files import KNOBS, epics, sim, write_prior


def options_of(tmp_path, data):
    path = tmp_path / "run.yaml"
    path.write_text(yaml.safe_dump(data))
    return RunSetup(config=load_config(path), optimizer=None, machine=None).options()


def test_objective_range_and_noise_reach_the_loop(tmp_path):
    """objective_range is passed as given; the stated noise is objective_noise first, then the
    simulated machine's noise, then the prior's, else none (the outlier rule is then off)."""
    opts = options_of(tmp_path, sim(objective_range=[0.0, 5.0], objective_noise=0.02))
    assert opts.objective_range == (0.0, 5.0) and opts.noise == 0.02
    assert options_of(tmp_path, sim()).noise == 0.04  # the simulated machine's
    assert options_of(tmp_path, sim()).objective_range is None
    quiet = sim(machine={"kind": "sim", "error_seed": 1, "noise": 0.0})
    assert options_of(tmp_path, quiet).noise is None
    write_prior(tmp_path / "prior.json", KNOBS)
    with_prior = {**quiet, "prior": "prior.json", "method": {"name": "pigp"}}
    assert options_of(tmp_path, with_prior).noise == 0.04  # the prior's


@pytest.mark.parametrize(
    ("over", "message"),
    [
        ({"objective_range": [5.0, 1.0]}, "objective_range: lower 5.0 must be below upper 1.0"),
        ({"objective_noise": 0.0}, "objective_noise"),
        ({"objective_noise": -1.0}, "objective_noise"),
    ],
)
def test_bad_reading_options_are_refused(tmp_path, over, message):
    path = tmp_path / "run.yaml"
    path.write_text(yaml.safe_dump(sim(**over)))
    with pytest.raises(ConfigError, match=message):
        load_config(path)


def test_an_epics_run_without_stated_noise_measures_it(tmp_path):
    """kind: epics stating no noise measures it at the start (noise_reads, default 5, 3 to 50;
    the plan says so, with its unit); with objective_noise, or on the simulator (whose noise is
    known), nothing is measured; machine.refuse_severity takes MAJOR or INVALID only."""
    from pigp_torch.commands.optimize_output import noise_in_force

    setup = RunSetup(config=validate(tmp_path, epics()), optimizer=None, machine=None)
    assert setup.options().noise is None and setup.options().noise_reads == 5
    assert noise_in_force(setup, None) == (
        "measured at the start: the standard deviation of 5 readings at the initial setting "
        "(at least 1% of their mean), in mA/min"
    )
    assert options_of(tmp_path, epics(noise_reads=12)).noise_reads == 12
    stated = RunSetup(config=validate(tmp_path, epics(objective_noise=0.03)), optimizer=None,
                      machine=None)  # fmt: skip
    assert stated.options().noise_reads == 0
    assert noise_in_force(stated, None) == "0.03 mA/min (stated: objective_noise)"
    assert options_of(tmp_path, sim()).noise_reads == 0
    for bad in (2, 51):
        with pytest.raises(ConfigError, match="noise_reads"):
            validate(tmp_path, epics(noise_reads=bad))
    major = {"kind": "epics", "settle_time": 0.0, "refuse_severity": "MAJOR"}
    assert validate(tmp_path, epics(machine=major)).machine.refuse_severity == "MAJOR"
    with pytest.raises(ConfigError, match="refuse_severity"):
        validate(tmp_path, epics(machine={**major, "refuse_severity": "MINOR"}))


def validate(tmp_path, data):
    path = tmp_path / "run.yaml"
    path.write_text(yaml.safe_dump(data))
    return load_config(path)
