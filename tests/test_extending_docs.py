"""docs/extending.md runs: its Python blocks, its run file and its commands (so the page that
says what an extension costs cannot drift from the package)."""

from __future__ import annotations

import re
import shlex
import shutil
from pathlib import Path

import pytest

DOC = Path(__file__).resolve().parents[1] / "docs" / "extending.md"
FENCE = re.compile(r"^```(\w+)\n(.*?)^```$", re.MULTILINE | re.DOTALL)


def blocks(language: str) -> list[str]:
    """The fenced blocks of ``language`` in the page, in order."""
    text = DOC.read_text(encoding="utf-8")
    return [body for lang, body in FENCE.findall(text) if lang == language]


#: Blocks of section (f), run by tests/test_extending_kinds_doc.py: the kind's folder and its use.
KIND_BLOCKS = ("# file:", "# kind:")


def fast_blocks() -> list[str]:
    return [b for b in blocks("python") if not b.startswith(("# slow", *KIND_BLOCKS))]


def slow_blocks() -> list[str]:
    return [b for b in blocks("python") if b.startswith("# slow")]


@pytest.fixture
def registry():
    """The method registry, restored after the test (the page registers methods)."""
    from pigp_torch.methods import METHODS

    saved = dict(METHODS)
    yield METHODS
    METHODS.clear()
    METHODS.update(saved)


@pytest.fixture
def user_folder(tmp_path, monkeypatch):
    """A folder holding the user's lattice file ``my_ring.json`` (SPEAR3's design deck), the
    working directory of the test."""
    from pigp_torch.simulation.deck import deck_path

    shutil.copy(deck_path("design"), tmp_path / "my_ring.json")
    monkeypatch.chdir(tmp_path)
    return tmp_path


def test_the_page_has_every_section_and_its_code():
    """Sections (a)-(f), each with code; the fast blocks and the slow ones are both there."""
    text = DOC.read_text(encoding="utf-8")
    for section in ("## (a)", "## (b)", "## (c)", "## (d)", "## (e)", "## (f)"):
        assert section in text
    assert len(fast_blocks()) >= 8 and len(slow_blocks()) == 1
    assert len(blocks("yaml")) == 2 and len(blocks("bash")) == 1


def test_the_python_blocks_run(registry):
    """Every fast block runs, in order, in one namespace (each asserts its own numbers): the
    acquisitions, the posterior, the recipe and the machine of the page."""
    namespace: dict = {"__name__": "extending_docs"}
    for code in fast_blocks():
        exec(compile(code, str(DOC), "exec"), namespace)  # our own page's code
    assert {"quadratic-ucb", "pigp-fast-pi"} <= set(registry)


@pytest.mark.slow  # builds the lattice file's ring three times (seconds each)
def test_the_lattice_ring_runs_in_python_a_run_file_and_the_cli(user_folder, capsys):
    """Section (e): the ring of the user's lattice file gives a prior (Python), and the page's
    run file and commands run on it (exit code 0; the run log holds the budget)."""
    from pigp_torch.cli import main
    from pigp_torch.data.runlog import read_log

    for code in slow_blocks():
        exec(compile(code, str(DOC), "exec"), {"__name__": "extending_docs"})
    (run_file,) = [b for b in blocks("yaml") if b.startswith("# my_ring.yaml")]
    name = run_file.splitlines()[0].removeprefix("# ").split(":")[0]
    (user_folder / name).write_text(run_file)
    for line in blocks("bash")[0].splitlines():
        argv = shlex.split(line)
        assert argv[0] == "pigp" and main(argv[1:]) == 0, line
    log = read_log(user_folder / "my_ring.jsonl")
    assert log.n_evaluations == 12 and log.last_end["status"] == "completed"
    assert (user_folder / "my_ring_data.npz").exists()
