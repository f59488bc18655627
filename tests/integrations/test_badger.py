"""A Badger routine (the real badger-opt package, its Python API, no display) runs the
pigp_physics generator on the pigp_sim environment against the simulated IOC on 127.0.0.1."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import pytest

pytest.importorskip("badger")
pytest.importorskip("caproto")

DRIVER = textwrap.dedent(
    """
    import json, math, sys
    import torch
    from badger.settings import init_settings
    import pigp_torch.integrations.badger as pb

    init_settings().write_value("BADGER_PLUGIN_ROOT", str(pb.plugin_root()))
    from badger.routine import Routine
    from badger.core import run_routine
    from xopt.generators import get_generator
    from pigp_torch.simulated_epics.ioc import start_sim_ioc
    from pigp_torch.prior import PhysicsPrior
    from pigp_torch.integrations.xopt_physics import PhysicsGenerator
    from gest_api.vocs import VOCS
    import pandas as pd

    d = len(pb.SIM_KNOBS)
    prior = PhysicsPrior(
        x0=torch.zeros(d, dtype=torch.float64), f_x0=1.5, f_inf=0.2,
        precision=2e-3 * torch.eye(d, dtype=torch.float64), amplitude=0.1, noise=0.04,
        knob_names=list(pb.SIM_KNOBS),
        bounds=torch.tensor([[-30.0] * d, [30.0] * d], dtype=torch.float64),
    )
    assert get_generator("pigp_physics") is PhysicsGenerator
    with start_sim_ioc(1) as ioc:
        vocs = VOCS(variables={k: [-30.0, 30.0] for k in pb.SIM_KNOBS},
                    objectives={"loss_rate": "MAXIMIZE"})
        gen = PhysicsGenerator(vocs=vocs, prior=prior, max_travel_distances=0.05, n_starts=2)
        routine = Routine(
            name="pigp-physics on the simulated ring", generator=gen,
            environment={"name": "pigp_sim", "ca_port": ioc.port},
            initial_points=pd.DataFrame([dict.fromkeys(pb.SIM_KNOBS, 0.0)]),
        )
        from badger.errors import BadgerRunTerminated

        results = []  # Badger's way to stop a run: the active callback says 2 (killed)
        try:
            run_routine(routine, lambda: 2 if len(results) >= 4 else 0, lambda c: None,
                        results.append, None, verbose=0)
        except BadgerRunTerminated:
            pass
        data = routine.data
        xs = torch.tensor(data[list(pb.SIM_KNOBS)].to_numpy())
        print(json.dumps({"n": len(data), "y": data["loss_rate"].tolist(),
                          "max_move": float((xs[1:] - xs[:-1]).abs().max()),
                          "told": routine.generator.optimizer.n_told}))
    """
)


@pytest.mark.slow
def test_a_badger_routine_runs_pigp_physics_over_channel_access(tmp_path):
    env = {**os.environ, "HOME": str(tmp_path), "QT_QPA_PLATFORM": "offscreen"}
    # Badger writes $HOME/.config/config.yaml but does not create the folder (an existing
    # user's home has it; before the package root imported lazily, matplotlib made it)
    (tmp_path / ".config").mkdir()
    proc = subprocess.run(
        [sys.executable, "-c", DRIVER], capture_output=True, text=True, timeout=300, env=env,
        cwd=tmp_path,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    import json

    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert result["n"] == 4 and all(0 < y < 10 for y in result["y"])
    assert result["max_move"] <= 0.05 * 60 + 1e-6  # the step limit, 3 A
    assert result["told"] >= 3


def test_plugin_root_holds_the_shipped_environment(tmp_path):
    """plugin_root() names the package's badger_plugins folder (with the pigp_sim environment)
    and install_plugins copies that environment into another root, once."""
    import pigp_torch.integrations.badger as pb

    env = pb.plugin_root() / "environments" / "pigp_sim"
    assert (env / "__init__.py").is_file()
    copied = pb.install_plugins(tmp_path)
    assert (copied / "__init__.py").read_text() == (env / "__init__.py").read_text()
    with pytest.raises(FileExistsError):
        pb.install_plugins(tmp_path)


def test_install_plugins_replaces_its_own_copy_on_request(tmp_path):
    """install_plugins(replace=True) overwrites an older copy of pigp_sim (an upgrade)."""
    import pigp_torch.integrations.badger as pb

    copied = pb.install_plugins(tmp_path)
    (copied / "__init__.py").write_text("old\n")
    again = pb.install_plugins(tmp_path, replace=True)
    assert again == copied
    shipped = pb.plugin_root() / "environments" / "pigp_sim" / "__init__.py"
    assert (again / "__init__.py").read_text() == shipped.read_text()


SETUP_DRIVER = textwrap.dedent(
    """
    import json, sys
    import pigp_torch.integrations.badger as pb

    first = pb.setup(site_dir=sys.argv[1])
    second = pb.setup(site_dir=sys.argv[1])
    from badger.settings import init_settings

    s = init_settings()
    print(json.dumps({"first": first, "second": second,
                      "paths": s.list_path_settings()}))
    """
)


def _fresh_home_env(tmp_path):
    env = {**os.environ, "HOME": str(tmp_path / "home"), "QT_QPA_PLATFORM": "offscreen"}
    for key in ("XDG_CONFIG_HOME", "XDG_DATA_HOME", "XDG_CACHE_HOME"):
        env[key] = str(tmp_path / "home" / key.lower())
    (tmp_path / "home").mkdir()
    return env


def test_setup_writes_badgers_config_on_a_fresh_home(tmp_path):
    """On a HOME without ~/.config, setup creates Badger's config file with every folder set
    (Badger's own first-use layout under ~/.local/share/Badger), copies pigp_sim into the
    plugin root and writes the one-line start-up file; run twice, it keeps the same settings."""
    site = tmp_path / "site"
    proc = subprocess.run(
        [sys.executable, "-c", SETUP_DRIVER, str(site)], capture_output=True, text=True,
        timeout=120, env=_fresh_home_env(tmp_path), cwd=tmp_path,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    import json

    import pigp_torch.integrations.badger as pb

    r = json.loads(proc.stdout.strip().splitlines()[-1])
    home = tmp_path / "home"
    assert r["first"]["config"] == str(home / ".config" / "config.yaml")
    assert (home / ".config" / "config.yaml").is_file()
    root = home / ".local" / "share" / "Badger" / "plugins"
    assert r["first"]["plugin root"] == str(root)
    assert (root / "environments" / "pigp_sim" / "configs.yaml").is_file()
    assert (root / "environments" / "sphere_2d").is_dir()  # Badger's own first-use set-up
    assert all(v is not None for v in r["paths"].values())  # Badger asks for none at start
    assert r["paths"]["BADGER_PLUGIN_ROOT"] == str(root)
    assert r["second"] == r["first"]
    assert (site / pb.STARTUP_FILE).read_text() == pb.STARTUP_LINE


HOOK_DRIVER = textwrap.dedent(
    """
    import json, site, sys
    site.addsitedir(sys.argv[1])  # processes the .pth file as the interpreter start does
    heavy = "pigp_torch.integrations.xopt_physics" in sys.modules
    import xopt.generators

    before = "pigp_physics" in xopt.generators.generators
    from badger.factory import list_generators

    print(json.dumps({"imported_at_start": heavy, "before": before,
                      "generators": list_generators()}))
    """
)


def test_the_startup_file_makes_badger_list_pigp_physics(tmp_path):
    """With setup's start-up file processed (as Python's site does at start), importing Badger's
    plugin registry registers pigp_physics, which Badger then lists; nothing heavy is imported
    before Badger is."""
    import json

    import pigp_torch.integrations.badger as pb

    env = _fresh_home_env(tmp_path)
    site = tmp_path / "site"
    site.mkdir()
    (site / pb.STARTUP_FILE).write_text(pb.STARTUP_LINE)
    cfg = tmp_path / "home" / ".config"
    cfg.mkdir()
    (cfg / "config.yaml").write_text(
        f"BADGER_PLUGIN_ROOT:\n  value: {pb.plugin_root()}\n  is_path: true\n"
    )
    proc = subprocess.run(
        [sys.executable, "-c", HOOK_DRIVER, str(site)], capture_output=True, text=True,
        timeout=120, env=env, cwd=tmp_path,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    r = json.loads(proc.stdout.strip().splitlines()[-1])
    assert r["imported_at_start"] is False and r["before"] is False
    assert "pigp_physics" in r["generators"] and "upper_confidence_bound" in r["generators"]


def test_a_generator_reads_its_prior_from_a_json_file(tmp_path):
    """prior or prior_file: PATH (what an operator types into Badger's generator settings)
    gives the same stored prior as the object; the file wins over an empty prior; a missing
    file is a validation error naming it, no prior at all one that says so."""
    import pydantic
    import torch
    from gest_api.vocs import VOCS

    from pigp_torch.integrations.xopt_physics import PhysicsGenerator
    from pigp_torch.prior import PhysicsPrior

    d = 2
    prior = PhysicsPrior(
        x0=torch.zeros(d, dtype=torch.float64), f_x0=1.5, f_inf=0.2,
        precision=torch.eye(d, dtype=torch.float64), amplitude=0.1, noise=0.04,
        knob_names=["a", "b"], bounds=torch.tensor([[-1.0, -1.0], [1.0, 1.0]]).double(),
    )  # fmt: skip
    prior.save(tmp_path / "prior.json")
    vocs = VOCS(variables={"a": [-1.0, 1.0], "b": [-1.0, 1.0]}, objectives={"y": "MAXIMIZE"})
    from_file = PhysicsGenerator(vocs=vocs, prior=str(tmp_path / "prior.json"))
    assert from_file.prior == PhysicsGenerator(vocs=vocs, prior=prior).prior
    with pytest.raises(pydantic.ValidationError, match=r"missing\.json"):
        PhysicsGenerator(vocs=vocs, prior=str(tmp_path / "missing.json"))
    # Badger's settings editor sends prior_file and whatever it made of the prior's arrays
    gui = PhysicsGenerator(vocs=vocs, prior={}, prior_file=str(tmp_path / "prior.json"))
    assert gui.prior == from_file.prior and gui.prior_file == str(tmp_path / "prior.json")
    with pytest.raises((pydantic.ValidationError, ValueError), match="no prior"):
        PhysicsGenerator(vocs=vocs)


def test_badger_can_list_the_generators_defaults():
    """Badger's `badger generator pigp_physics` and its GUI show Xopt's
    get_generator_defaults: plain values (no unset default-factory marker), prior required."""
    from xopt.generators import get_generator_defaults

    import pigp_torch.integrations.xopt_physics  # noqa: F401  (registration)

    defaults = get_generator_defaults("pigp_physics")
    assert defaults["prior"] is None and defaults["options"] == {}
    assert defaults["beta"] == 4.0 and defaults["step_limit"] == 0.6
