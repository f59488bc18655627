"""docs/own_ring.md runs as written: generate-data -> train-surrogate -> build-prior -> run file
-> optimize -> report on a 3-knob ring from the shipped SPEAR3 design deck, in a fresh folder."""

from __future__ import annotations

import math
import re
import shlex
from pathlib import Path

import pytest
import torch

from pigp_torch import cli
from pigp_torch.data.runlog import read_log
from pigp_torch.loop.run import load_config
from pigp_torch.prior import PhysicsPrior

REPO = Path(__file__).resolve().parents[1]
PAGE = REPO / "docs" / "own_ring.md"
KNOBS = ["01G-QSS4", "02G-QSS3", "05G-QSS3"]


def _page_blocks():
    text = PAGE.read_text(encoding="utf-8")
    (bash,) = re.findall(r"```bash\n(.*?)```", text, re.S)
    (run_file,) = re.findall(r"```yaml\n(.*?)```", text, re.S)
    commands = [shlex.split(c) for c in bash.replace("\\\n", " ").splitlines() if c.strip()]
    return commands, run_file


@pytest.mark.slow
def test_the_own_ring_page_runs_as_written(tmp_path, monkeypatch, capsys):
    """Each command of the page exits 0 in order; the prior and the run log exist, the prior's
    optimum and every setting lie inside the ±30 A box, and every number is finite."""
    commands, run_file = _page_blocks()
    assert [c[:2] for c in commands] == [["pigp", "generate-data"], ["pigp", "train-surrogate"],
                                         ["pigp", "build-prior"], ["pigp", "optimize"],
                                         ["pigp", "report"]]  # fmt: skip
    (tmp_path / "pigp_torch").symlink_to(REPO / "pigp_torch")  # the page's relative paths
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("PIGP_LOCK_DIR", str(tmp_path / "locks"))
    (tmp_path / "runs").mkdir()
    (tmp_path / "runs" / "my_ring.yaml").write_text(run_file)  # step 4: the run file
    for command in commands:
        assert cli.main(command[1:]) == 0, command
    out = capsys.readouterr().out

    prior = PhysicsPrior.load(tmp_path / "runs" / "my_ring_prior.json")
    assert prior.knob_names == KNOBS and prior.center_cov.shape == (3, 3)
    assert bool(torch.isfinite(prior.precision).all()) and prior.condition_number >= 1
    assert bool((prior.x0.abs() <= 30.0).all()) and 0.098 < prior.f_x0 < 2.0  # mA/min

    config = load_config(tmp_path / "runs" / "my_ring.yaml")
    assert config.method.name == "pigp-physics" and config.machine.error_seed == 2
    log = read_log(tmp_path / "runs" / "my_ring.jsonl")
    assert log.n_evaluations == 15 and log.header["knob_names"] == KNOBS
    X, Y = log.X(), log.Y()
    assert bool((X.abs() <= 30.0).all()) and all(math.isfinite(y) for y in Y.tolist())
    assert bool((Y > 0.05).all()) and bool((Y < 1.5).all())  # loss rates of this ring, mA/min
    step, _, best = log.best()
    assert f"best y = {best:.6g} mA/min at evaluation {step + 1}" in out
    assert best > float(Y[0])  # the run found a higher loss rate than at the start
    assert log.last_end["final_knobs"] == [0.0, 0.0, 0.0]  # restored to where it started
    assert (tmp_path / "runs" / "my_ring_report.png").stat().st_size > 10_000
