"""Every run file in examples/ passes `pigp optimize --config F --dry-run` as shipped, and the
examples of the ring's machine kinds run the default method with the prior that ships with the
package (`prior: builtin:spear3`)."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest
import yaml

from pigp_torch import cli
from pigp_torch.data import BUILTIN_PRIORS, builtin_prior
from pigp_torch.loop.config import ConfigError
from pigp_torch.loop.run import load_config
from pigp_torch.prior import PhysicsPrior

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"
RUN_FILES = sorted(p.name for p in EXAMPLES.glob("*.yaml"))
#: the default method of each machine kind (what its example must run)
DEFAULT_METHOD = {"sim": "pigp-physics", "epics": "pigp-physics", "ares-sim": "ares-physics"}


def test_there_is_an_example_per_machine_kind():
    kinds = {yaml.safe_load((EXAMPLES / n).read_text())["machine"]["kind"] for n in RUN_FILES}
    assert kinds == set(DEFAULT_METHOD)


@pytest.mark.parametrize("name", RUN_FILES)
def test_an_example_uses_its_kinds_default_method_and_a_shipped_prior(name):
    config = load_config(EXAMPLES / name)
    assert config.method.name == DEFAULT_METHOD[config.machine.kind]
    if config.method.name == "pigp-physics":  # the ring's method needs a prior: the shipped one
        assert config.prior == builtin_prior("builtin:spear3")
        assert config.prior.is_relative_to(Path(cli.__file__).resolve().parent)


def test_the_shipped_prior_is_the_kept_one_with_its_ensemble_fields():
    """pigp_torch/data/priors/spear3.json is the byte copy of docs/data's kept prior, loads, and
    carries the centre covariance and shape that pigp-physics reads."""
    shipped = builtin_prior("spear3")
    kept = EXAMPLES.parent / "docs" / "data" / "prior_spear3_seed0_surrogate.json"
    assert shipped.read_bytes() == kept.read_bytes()
    prior = PhysicsPrior.load(shipped)
    assert len(prior.knob_names) == 13 and prior.center_cov is not None
    assert prior.bounds.abs().max().item() == 30.0  # amps of the windings
    assert json.loads(shipped.read_text())["provenance"]["source"] == "surrogate"
    assert set(BUILTIN_PRIORS) == {"spear3"}


def test_an_unknown_shipped_prior_is_one_clear_error(tmp_path):
    data = yaml.safe_load((EXAMPLES / "run_sim.yaml").read_text())
    data["prior"] = "builtin:spear4"
    (tmp_path / "run.yaml").write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match=r"no shipped prior 'builtin:spear4'.*builtin:spear3"):
        load_config(tmp_path / "run.yaml")


def _dry_run(path: Path, capsys) -> str:
    assert cli.main(["optimize", "--config", str(path), "--dry-run"]) == 0
    return capsys.readouterr().out


@pytest.mark.parametrize("name", RUN_FILES)
def test_every_example_passes_the_dry_run(name, capsys, monkeypatch, tmp_path):
    """`pigp optimize --config examples/F --dry-run` as the README gives it: the plan is printed
    and nothing is written (the EPICS example against the simulated IOC on 127.0.0.1)."""
    monkeypatch.setenv("PIGP_LOCK_DIR", str(tmp_path / "locks"))
    path = EXAMPLES / name
    config = load_config(path)
    before = config.log.stat().st_mtime_ns if config.log.exists() else None
    kind = config.machine.kind
    if kind == "ares-sim" and importlib.util.find_spec("cheetah") is None:
        pytest.skip("the ares extra (cheetah-accelerator) is not installed")
    if kind == "epics":
        if importlib.util.find_spec("caproto") is None:
            pytest.skip("the epics extra (caproto) is not installed")
        from pigp_torch.simulated_epics.ioc import start_sim_ioc

        with start_sim_ioc(1, update_period=0.05):  # the ring `pigp serve-sim` serves
            out = _dry_run(path, capsys)
    else:
        out = _dry_run(path, capsys)
    assert f"plan: {config.method.name} on the " in out and "dry run" in out
    for knob in config.knob_names:
        assert knob in out
    if config.prior is not None:
        assert f"prior {config.prior}" in out
    if kind == "sim":  # every number with its unit
        assert "reading noise 0.04 mA/min" in out and "objective floor 0.1 mA/min" in out
    after = config.log.stat().st_mtime_ns if config.log.exists() else None
    assert after == before  # the run log is neither made nor touched


def test_a_bound_outside_the_simulated_ring_is_refused_with_its_unit(tmp_path, capsys):
    data = yaml.safe_load((EXAMPLES / "run_sim.yaml").read_text())
    data["knobs"]["01G-QSS4"] = [-40, 40]
    data["log"] = str(tmp_path / "run.jsonl")
    (tmp_path / "run.yaml").write_text(yaml.safe_dump(data))
    assert cli.main(["optimize", "--config", str(tmp_path / "run.yaml"), "--dry-run"]) == 2
    assert "bounds outside the simulator's range [-30, 30] A" in capsys.readouterr().err
