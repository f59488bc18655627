"""Observables over real Channel Access: a run file's ``observable_pvs`` are read after each
objective reading of the simulated IOC, kept in the run log with names and units, and refused
when their units do not name them all."""

from __future__ import annotations

import pytest
import yaml

from pigp_torch import cli
from pigp_torch.data.runlog import read_log
from pigp_torch.loop.config import ConfigError
from pigp_torch.loop.run import validate_config
from tests.epics.ca_runs import KNOBS, start_of, write_config


@pytest.fixture(autouse=True)
def private_locks(tmp_path, monkeypatch):
    monkeypatch.setenv("PIGP_LOCK_DIR", str(tmp_path / "locks"))
    modules = tuple(dict.fromkeys((*cli.COMMAND_MODULES, "optimize")))
    monkeypatch.setattr(cli, "COMMAND_MODULES", modules)


def observed(ioc, units=True) -> dict:
    """The two knobs' readback PVs as observables (what the IOC serves at each reading)."""
    pvs = {f"rb_{i}": pv for i, pv in enumerate(ioc.readback_pvs[:2])}
    machine = {"kind": "epics", "settle_time": 0.1, "timeout": 1.0, "stale_timeout": 1.0,
               "observable_pvs": pvs}  # fmt: skip
    if units:
        machine["observable_units"] = {"rb_0": "A", "rb_1": "A"}
    return machine


def test_the_log_keeps_the_observables_the_ioc_serves(ioc, probe, ring, tmp_path, capsys):
    """5 evaluations of Nelder-Mead with the knobs' readbacks as observables: the header names
    them with units, and every evaluation keeps the values read over CA, which equal the
    setting the IOC reached (its readbacks follow the setpoints exactly)."""
    probe.write_many(ioc.setpoint_pvs[:2], start_of(ring))
    config = write_config(tmp_path, ioc, ring, budget=5, machine=observed(ioc))
    assert cli.main(["optimize", "--config", config, "--quiet"]) == 0, capsys.readouterr().err
    log = read_log(tmp_path / "run.jsonl")
    assert log.knob_names == KNOBS and log.n_evaluations == 5
    assert log.observable_names == ["rb_0", "rb_1"] and log.observable_units == ["A", "A"]
    obs = log.observables()
    assert obs is not None and obs.shape == (5, 2)
    assert (obs - log.X()).abs().max() <= 1e-12
    assert len({tuple(x) for x in obs.tolist()}) == 5  # five settings, five different readings


def test_observable_units_must_name_every_observable(ioc, ring, tmp_path):
    """observable_units naming other observables than observable_pvs: one ConfigError line."""
    data = yaml.safe_load(open(write_config(tmp_path, ioc, ring, machine=observed(ioc))).read())
    data["machine"]["observable_units"] = {"rb_0": "A"}
    with pytest.raises(ConfigError, match=r"machine\.observable_units: name the unit of every"):
        validate_config(data, base_dir=tmp_path)
