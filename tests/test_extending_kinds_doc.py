"""Section (f) of docs/extending.md runs: the page's folder of a third machine kind is written out
as ``transfer_line/__init__.py``, found by the registry in a fresh interpreter (as a folder under
``pigp_torch/machines`` is; nothing else of the package is edited), used from Python (the page's
block asserts the registry, the method, the contract, the prior and a tuned run) and run through
``pigp optimize`` with the page's run file (its plan first, ``--dry-run``), then ``pigp report``
of its log (the kind's true curve)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from tests.test_extending_docs import DOC, blocks

ROOT = Path(__file__).resolve().parents[1]

#: The fresh interpreter: the kinds' folder gets the written-out one, then the page's block and
#: ``pigp optimize`` run.
SCRIPT = """
import sys
import pigp_torch.machines as machines

machines.__path__.append(sys.argv[1])
namespace = {"__name__": "extending_kinds"}
exec(compile(open(sys.argv[2]).read(), sys.argv[2], "exec"), namespace)
from pigp_torch.cli import main

assert main(["optimize", "--config", sys.argv[3], "--dry-run"]) == 0
assert main(["optimize", "--config", sys.argv[3], "--quiet"]) == 0
sys.exit(main(["report", "line.jsonl", "-o", "line_report"]))
"""


def _block(prefix: str, language: str = "python") -> str:
    (block,) = [b for b in blocks(language) if b.startswith(prefix)]
    return block


def test_a_new_machine_kind_is_one_folder(tmp_path):
    folder = tmp_path / "kinds" / "transfer_line"
    folder.mkdir(parents=True)
    file_block = _block("# file: pigp_torch/machines/transfer_line/__init__.py")
    (folder / "__init__.py").write_text(file_block)
    (tmp_path / "use.py").write_text(_block("# kind:"))
    (tmp_path / "line.yaml").write_text(_block("# line.yaml", "yaml"))
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    done = subprocess.run(
        [sys.executable, "-c", SCRIPT, str(folder.parent), "use.py", "line.yaml"],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    plan = "plan: line-physics on the simulated transfer line: 2 correctors, a doublet, a screen"
    assert plan in done.stdout
    records = [json.loads(line) for line in (tmp_path / "line.jsonl").read_text().splitlines()]
    evaluations = [r for r in records if r.get("type") == "evaluation"]
    assert len(evaluations) == 10
    assert all(len(r["observables"]) == 4 for r in evaluations)  # the screen's four numbers
    assert records[-1]["status"] == "completed"
    page = (tmp_path / "line_report.html").read_text()  # the kind's true curve, in m
    assert "best true value" in page and "true optimum" not in page  # no search: none offered
    assert str(DOC).endswith("extending.md")
