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
    from pigp_torch.testing.ioc import start_sim_ioc
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
