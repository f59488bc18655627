"""`pigp` answers its help, a usage error and an invalid run file without importing the heavy
packages (torch, BoTorch, pyAT, pandas, ...): which modules are loaded is checked, not how long it
takes (machine-independent; ``benchmarks/cli_startup.py`` measures the time)."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: packages that must not be imported to answer the commands below (top-level module names)
HEAVY = (
    "torch",
    "botorch",
    "gpytorch",
    "at",
    "pandas",
    "matplotlib",
    "scipy",
    "cheetah",
    "caproto",
    "p4p",
    "xopt",
    "badger",
)

#: run in a fresh interpreter (the test process has torch loaded already): ``pigp ARGV`` through
#: :func:`pigp_torch.cli.main`, then the exit status, stderr's first line and the heavy modules
SCRIPT = """
import contextlib, io, json, sys
from pigp_torch.cli import main
err = io.StringIO()
with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
    try:
        code = main(json.loads(sys.argv[1]))
    except SystemExit as e:
        code = e.code
heavy = json.loads(sys.argv[2])
loaded = sorted({m.split(".")[0] for m in sys.modules} & set(heavy))
print(json.dumps({"code": code, "err": err.getvalue(), "loaded": loaded}))
"""


def _answer(argv: list[str], cwd: Path) -> dict:
    proc = subprocess.run(
        [sys.executable, "-c", SCRIPT, json.dumps(argv), json.dumps(HEAVY)],
        capture_output=True,
        text=True,
        cwd=cwd,
        timeout=120,
        check=True,
    )
    return json.loads(proc.stdout)


@pytest.fixture
def typo_run_file(tmp_path) -> Path:
    """The shipped simulated-ring run file with one key misspelt (``budgte``)."""
    text = (ROOT / "examples" / "run_sim.yaml").read_text(encoding="utf-8")
    assert "\nbudget:" in text
    path = tmp_path / "typo.yaml"
    path.write_text(text.replace("\nbudget:", "\nbudgte:"), encoding="utf-8")
    return path


def test_help_loads_no_heavy_package(tmp_path):
    """``pigp --help`` and each command's help (``optimize --help`` excepted: it names the methods
    of the registry, which is read when that help is shown)."""
    commands = ["generate-data", "train-surrogate", "build-prior", "compare", "demo"]
    commands += ["serve-sim", "badger-setup", "report", "bench simulator", "bench bo"]
    for argv in [["--help"], *([*c.split(), "--help"] for c in commands)]:
        got = _answer(argv, tmp_path)
        assert got["code"] == 0, argv
        assert got["loaded"] == [], (argv, got["loaded"])


def test_usage_error_loads_no_heavy_package(tmp_path):
    got = _answer(["optimize"], tmp_path)
    assert got["code"] == 2
    assert got["err"].startswith("pigp optimize: error: give a run file with --config")
    assert got["loaded"] == []


def test_run_file_typo_is_refused_without_heavy_packages(tmp_path, typo_run_file):
    got = _answer(["optimize", "--config", str(typo_run_file)], tmp_path)
    assert got["code"] == 2
    assert "unknown key 'budgte' (did you mean 'budget'?)" in got["err"]
    assert got["loaded"] == []


def test_a_valid_run_file_goes_on_to_the_full_check(tmp_path, typo_run_file):
    """The guard is not vacuous: a dry run of a valid file does import torch (the optimizer)."""
    good = typo_run_file.with_name("good.yaml")
    text = typo_run_file.read_text(encoding="utf-8").replace("\nbudgte:", "\nbudget:")
    good.write_text(text.replace("../runs/run_sim.jsonl", "run.jsonl"), encoding="utf-8")
    got = _answer(["optimize", "--config", str(good), "--dry-run"], tmp_path)
    assert got["code"] == 0, got["err"]
    assert "torch" in got["loaded"]
