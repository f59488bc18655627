"""The run file's reading options reach the loop: objective_range, and the stated noise of one
reading (objective_noise, else the simulated machine's noise, else the prior's)."""

from __future__ import annotations

import pytest
import yaml

from pigp_torch.loop.config import ConfigError
from pigp_torch.loop.run import RunSetup, load_config
from tests.run.test_run_files import KNOBS, sim, write_prior


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
