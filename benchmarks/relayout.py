"""Move ``pigp_torch``'s plumbing into the pipeline's stage packages, and rewrite every reference.

A one-off maintenance tool, kept so that the move is reproducible: run it from the repository
root (or pass ``--root``) on any branch; it is idempotent (a second run changes nothing) and it
fixes files that arrive later from other branches (the rewrite is by module path, so re-running
it after a merge fixes new files that still import an old path).

    python benchmarks/relayout.py            # move and rewrite, printing what it did
    python benchmarks/relayout.py --dry-run  # print what it would do, change nothing
    python benchmarks/relayout.py --check    # exit 1 if anything is left to do

What it does, in order:

1. ``git mv`` each file of :data:`MOVES` (a directory move moves its files one by one, so files
   that appear later at an old place are moved too); a target that already exists is skipped
   when the source is gone, and reported as a conflict when both exist. Emptied old folders (and
   their ``__pycache__``) are removed. New stage packages get the ``__init__.py`` of
   :data:`NEW_PACKAGES`.
2. Rewrite references in every tracked (or untracked, not ignored) text file of the repository
   except this one and the shipped lattice tables: dotted module paths
   (``pigp_torch.runlog.writer`` -> ``pigp_torch.data.runlog.writer``, in code, strings,
   docstrings, Sphinx roles, notebooks' JSON), ``from pigp_torch import runlog``-style imports
   of a moved module, file paths (``pigp_torch/runlog/`` -> ``pigp_torch/data/runlog/``), and
   the few literal references of :data:`LITERAL_RULES` (file names the demo cache hashes).
3. Set ``LAYERS`` (and the table in the docstring) of ``tests/test_architecture.py`` to the new
   units; a unit it does not know (added on another branch) keeps its layer and is reported.
4. With ruff (when on ``PATH``), sort the imports and format the rewritten ``.py``/``.ipynb``
   files, and wrap the docstring lines the longer paths pushed past 100 columns.
5. Print what it cannot fix (paths joined from parts, quoted old file names, ``from`` imports
   mixing moved and unmoved modules, lines still too long, conflicts, units it does not know,
   an old README layout tree) as ``CHECK BY HAND`` lines, for a person to fix.

Run logs are not affected: they record method and class names, never module paths.
"""

from __future__ import annotations

import argparse
import io
import re
import shutil
import subprocess
import sys
import textwrap
import tokenize
from pathlib import Path

#: (old path, new path) relative to the repository root; a folder moves with everything in it.
MOVES: tuple[tuple[str, str], ...] = (
    ("pigp_torch/_utils.py", "pigp_torch/_utils/__init__.py"),
    ("pigp_torch/_lbfgsb.py", "pigp_torch/_utils/lbfgsb.py"),
    ("pigp_torch/_multistart.py", "pigp_torch/_utils/multistart.py"),
    ("pigp_torch/dataset.py", "pigp_torch/data/dataset.py"),
    ("pigp_torch/simulation/sampling.py", "pigp_torch/data/sampling.py"),
    ("pigp_torch/runlog", "pigp_torch/data/runlog"),
    ("pigp_torch/runlock.py", "pigp_torch/data/runlock.py"),
    ("pigp_torch/config", "pigp_torch/loop/config"),
    ("pigp_torch/run", "pigp_torch/loop/run"),
    ("pigp_torch/progress.py", "pigp_torch/loop/progress.py"),
    ("pigp_torch/ringargs.py", "pigp_torch/testing/ringargs.py"),
    ("pigp_torch/report.py", "pigp_torch/reporting/report.py"),
    ("pigp_torch/dashboard.py", "pigp_torch/reporting/dashboard.py"),
)

#: Packages the move creates, with their ``__init__.py`` (written only when absent).
NEW_PACKAGES: dict[str, str] = {
    "pigp_torch/data/__init__.py": (
        '"""Data of the chain: the shipped lattice decks (``*.json``, provenance in README.md),\n'
        "training sets drawn from a simulator (:mod:`~pigp_torch.data.dataset`,\n"
        ":mod:`~pigp_torch.data.sampling`), and run logs with their locks\n"
        "(:mod:`~pigp_torch.data.runlog`, :mod:`~pigp_torch.data.runlock`).\n\n"
        "Importing this package imports none of its modules (the lock module stays light).\n"
        '"""\n'
    ),
    "pigp_torch/reporting/__init__.py": (
        '"""Reports of finished and running runs: the HTML report of a run log\n'
        "(:mod:`~pigp_torch.reporting.report`) and the live dashboard\n"
        "(:mod:`~pigp_torch.reporting.dashboard`). Importing this package imports neither.\n"
        '"""\n'
    ),
}

#: Units of ``tests/test_architecture.py`` after the move: layer and a few words for its table.
NEW_LAYERS: dict[str, tuple[int, str]] = {
    "cli": (11, "the ``pigp`` parser"),
    "<root>": (11, "a lazy facade"),
    "commands": (10, "one module per ``pigp`` command"),
    "badger_plugins": (10, "Badger's entry point"),
    "benchmark": (9, "the protocol and the demo"),
    "reporting": (9, "run reports and the dashboard"),
    "loop": (8, "the run loop: the loop, run files (``config``), runs (``run``), progress"),
    "testing": (7, "the simulated ring as EPICS servers, ring options"),
    "methods": (6, "the method registry"),
    "machine": (6, "the Machine protocol and machines"),
    "integrations": (5, "Xopt and Badger glue"),
    "optimizers": (4, "ask/tell"),
    "models": (3, "GP builders, posteriors"),
    "data": (3, "datasets, sampling, run logs and locks, lattice decks"),
    "kernels": (2, ""),
    "prior": (2, ""),
    "surrogate": (2, ""),
    "simulation": (2, ""),
    "_utils": (0, "dtype and knob tensors, scipy's L-BFGS-B driven directly, multi-start"),
    "_version": (0, ""),
}

#: Units that the move dissolves into others.
OLD_UNITS = frozenset(
    {"_lbfgsb", "_multistart", "dataset", "runlog", "runlock", "config", "run", "progress",
     "ringargs", "report", "dashboard"}
)  # fmt: skip

SUFFIXES = {".py", ".ipynb", ".md", ".rst", ".txt", ".toml", ".cfg", ".ini", ".yaml", ".yml",
            ".sh", ".json", ".html", ""}  # fmt: skip
SKIP = re.compile(r"^(benchmarks/relayout\.py|pigp_torch/data/[^/]+\.json)$")


def _module(path: str) -> str:
    """``pigp_torch/a/b.py`` -> ``pigp_torch.a.b``; ``pigp_torch/a/__init__.py`` -> ``...a``."""
    p = path.removesuffix(".py").removesuffix("/__init__")
    return p.replace("/", ".")


#: Old dotted module path -> new one (only those whose name changes).
MODULE_MOVES = {_module(a): _module(b) for a, b in MOVES if _module(a) != _module(b)}
#: Old file path (no ``.py``) -> new one, for paths written in prose; ``_utils.py`` is special.
PATH_MOVES = {a.removesuffix(".py"): b.removesuffix(".py") for a, b in MOVES
              if not b.endswith("__init__.py")}  # fmt: skip

_alt = "|".join(re.escape(m.split(".", 1)[1]) for m in sorted(MODULE_MOVES, key=len, reverse=True))
DOTTED = re.compile(rf"(?<![\w.])pigp_torch\.({_alt})(?![\w])")
_palt = "|".join(re.escape(p.split("/", 1)[1]) for p in sorted(PATH_MOVES, key=len, reverse=True))
SLASHED = re.compile(rf"(?<![\w.])pigp_torch/({_palt})(?![\w-])")
UTILS_FILE = re.compile(r"(?<![\w.])pigp_torch/_utils\.py\b")
_NAME = r"[A-Za-z_]\w*(?:\s+as\s+[A-Za-z_]\w*)?"
FROM_IMPORT = re.compile(
    rf"\bfrom\s+(pigp_torch(?:\.\w+)*)\s+import\s+"
    rf"(\(\s*{_NAME}(?:\s*,\s*{_NAME})*\s*,?\s*\)|{_NAME}(?:[ \t]*,[ \t]*{_NAME})*)"
)


def _rewrite_from(match: re.Match, manual: list[str]) -> str:
    """``from pigp_torch import runlog`` -> ``from pigp_torch.data import runlog`` (and an
    ``as`` keeps the old name when the module's name changes)."""
    parent, names = match.group(1), match.group(2)
    items = [n.strip() for n in names.strip("()").split(",") if n.strip()]
    moved = {}
    for item in items:
        name, _, alias = (s.strip() for s in item.partition(" as "))
        full = f"{parent}.{name}"
        if full in MODULE_MOVES:
            new_parent, new_name = MODULE_MOVES[full].rsplit(".", 1)
            local = alias or name
            moved[item] = (new_parent, new_name if local == new_name else f"{new_name} as {local}")
    if not moved:
        return match.group(0)
    parents = {p for p, _ in moved.values()}
    if len(moved) != len(items) or len(parents) != 1:
        manual.append(f"mixed import, split it by hand: {match.group(0)!r}")
        return match.group(0)
    (new_parent,) = parents
    body = ", ".join(n for _, n in moved.values())
    return f"from {new_parent} import {f'({body})' if names.startswith('(') else body}"


def rewrite_text(text: str, manual: list[str]) -> str:
    text = FROM_IMPORT.sub(lambda m: _rewrite_from(m, manual), text)
    text = DOTTED.sub(lambda m: MODULE_MOVES[f"pigp_torch.{m.group(1)}"], text)
    text = UTILS_FILE.sub("pigp_torch/_utils/__init__.py", text)
    return SLASHED.sub(lambda m: PATH_MOVES[f"pigp_torch/{m.group(1)}"], text)


class Repo:
    def __init__(self, root: Path, dry: bool):
        self.root, self.dry, self.changes = root, dry, 0
        self.rewritten: list[str] = []

    def git(self, *args: str) -> str:
        return subprocess.run(["git", *args], cwd=self.root, check=True, capture_output=True,
                              text=True).stdout  # fmt: skip

    def files(self) -> list[str]:
        out = self.git("ls-files", "-z", "--cached", "--others", "--exclude-standard")
        return sorted({f for f in out.split("\0") if f and (self.root / f).is_file()})

    def tracked(self, path: str) -> bool:
        return bool(self.git("ls-files", "--", path).strip())

    def say(self, line: str) -> None:
        self.changes += 1
        print(("would " if self.dry else "") + line)


def move(repo: Repo) -> list[str]:
    conflicts = []
    files = repo.files()
    for old, new in MOVES:
        src = repo.root / old
        if src.is_dir():
            pairs = [(f, new + f[len(old) :]) for f in files if f.startswith(old + "/")]
        elif src.is_file():
            pairs = [(old, new)]
        else:
            continue
        for a, b in pairs:
            if (repo.root / b).exists():
                conflicts.append(f"both exist, merge by hand: {a} and {b}")
                continue
            repo.say(f"move {a} -> {b}")
            if repo.dry:
                continue
            (repo.root / b).parent.mkdir(parents=True, exist_ok=True)
            if repo.tracked(a):
                repo.git("mv", a, b)
            else:
                shutil.move(repo.root / a, repo.root / b)
        if src.is_dir() and not repo.dry:
            for cache in sorted(src.rglob("__pycache__"), reverse=True):
                shutil.rmtree(cache)
            for d in sorted((p for p in [src, *src.rglob("*")] if p.is_dir()), reverse=True):
                if not any(d.iterdir()):
                    d.rmdir()
    for path, text in NEW_PACKAGES.items():
        if not (repo.root / path).exists():
            repo.say(f"create {path}")
            if not repo.dry:
                (repo.root / path).write_text(text, encoding="utf-8")
                repo.git("add", path)
    return conflicts


def rewrite(repo: Repo, manual: list[str]) -> None:
    for f in repo.files():
        if SKIP.match(f) or (Path(f).suffix not in SUFFIXES and f != ".ci/run"):
            continue
        path = repo.root / f
        try:
            text = path.read_text(encoding="utf-8")
        except UnicodeDecodeError:
            continue
        notes: list[str] = []
        new = rewrite_text(text, notes)
        for rule_file, old, replacement in LITERAL_RULES:
            if f == rule_file:
                new = new.replace(old, replacement)
        manual += [f"{f}: {n}" for n in notes]
        if new != text:
            if f.endswith((".py", ".ipynb")):
                repo.rewritten.append(f)
            n = sum(a != b for a, b in zip(text.splitlines(), new.splitlines(), strict=False))
            repo.say(f"rewrite {f} ({n} lines)")
            if not repo.dry:
                path.write_text(new, encoding="utf-8")
        if f.endswith(".py"):
            for line in new.splitlines():
                if JOINED.search(line) or OLD_FILE_NAME.search(line):
                    manual.append(f"{f}: a path from parts or an old file name: {line.strip()}")
        if f == "README.md" and README_TREE.search(new):
            manual.append("README.md: the Layout tree still lists an old place; update it")


JOINED = re.compile(r"""(PACKAGE|pigp_torch["']?)\s*/\s*["'](""" + _palt + r""")\b""")
#: A file name of a moved top-level module, quoted (a path built from parts).
OLD_FILE_NAME = re.compile(
    r"""["'](_multistart|_lbfgsb|_utils|dataset|runlock|ringargs|progress|report|dashboard)\.py["']"""
)
#: The README's layout tree, listing a unit that moved.
README_TREE = re.compile(
    r"^  (runlog/|runlock\.py|config/|run/|report\.py|dashboard\.py|progress\.py)", re.M
)
#: (file, old text, new text): references the module-path rewrite cannot see.
LITERAL_RULES: tuple[tuple[str, str, str], ...] = (
    # the demo cache's digest covers these sources (data/ now holds dataset.py; _utils/ the rest)
    (
        "pigp_torch/benchmark/demo_cache.py",
        '"data", "_multistart.py", "_utils.py", "dataset.py")',
        '"data", "_utils")',
    ),
)
LAYERS_BLOCK = re.compile(r"^LAYERS: dict\[str, int\] = \{\n.*?^\}\n", re.M | re.S)
TABLE = re.compile(r"(^=+  =+\nlayer  units\n=+  =+\n)(.*?)(^=+  =+\n)", re.M | re.S)


def layers(repo: Repo, manual: list[str]) -> None:
    path = repo.root / "tests/test_architecture.py"
    if not path.is_file():
        manual.append("tests/test_architecture.py not found: LAYERS not set")
        return
    text = path.read_text(encoding="utf-8")
    block = LAYERS_BLOCK.search(text)
    if block is None:
        manual.append("tests/test_architecture.py: LAYERS block not found, set it by hand")
        return
    old = eval(block.group(0).split("=", 1)[1], {"ROOT": "<root>", "dict": dict})  # our own file
    table = {u: v for u, v in NEW_LAYERS.items()}
    for unit, layer in old.items():
        if unit not in table and unit not in OLD_UNITS:
            table[unit] = (layer, "")
            manual.append(f"unit {unit!r} kept at layer {layer}: check its place in LAYERS")
    by_layer: dict[int, list[str]] = {}
    for unit, (layer, _) in table.items():
        by_layer.setdefault(layer, []).append(unit)
    lines, rows = ["LAYERS: dict[str, int] = {"], []
    for layer in sorted(by_layer, reverse=True):
        units = by_layer[layer]
        names = [("ROOT" if u == "<root>" else f'"{u}"') for u in units]
        if len(names) == 1:
            lines.append(f"    {names[0]}: {layer},")
        else:
            lines.append(f"    **dict.fromkeys(({', '.join(names)}), {layer}),")
        words = [(f"``{u}``" if u != "<root>" else "the package root")
                 + (f" ({table[u][1]})" if table[u][1] else "")
                 for u in units]  # fmt: skip
        rows.append(textwrap.fill(", ".join(words), 100, initial_indent=f"{layer:<5}  ",
                                  subsequent_indent=" " * 7))  # fmt: skip
    new = text[: block.start()] + "\n".join(lines) + "\n}\n" + text[block.end() :]
    new = TABLE.sub(lambda m: m.group(1) + "\n".join(rows) + "\n" + m.group(3), new, count=1)
    if new != text:
        repo.say("set LAYERS in tests/test_architecture.py")
        if not repo.dry:
            path.write_text(new, encoding="utf-8")


def tidy(repo: Repo, manual: list[str]) -> None:
    """Sort the imports and format the rewritten Python files (longer module paths), with ruff;
    list the prose lines that are now too long (ruff cannot wrap a docstring or a comment)."""
    ruff = shutil.which("ruff")
    if ruff is None:
        manual.append("ruff not found: run `ruff check --fix --select I . && ruff format .`")
        return
    files = repo.rewritten
    subprocess.run([ruff, "check", "--fix", "--select", "I", "-q", *files], cwd=repo.root)
    subprocess.run([ruff, "format", "-q", *files], cwd=repo.root)
    for attempt in range(2):  # wrap the docstring lines now too long, then list what is left
        out = subprocess.run(
            [ruff, "check", "--select", "E501", "--output-format", "concise", *files],
            cwd=repo.root,
            capture_output=True,
            text=True,
        ).stdout
        long: dict[str, list[int]] = {}
        for line in out.splitlines():
            name, number = ([*line.split(":"), ""])[:2]
            if "E501" in line and name.endswith(".py") and number.isdigit():
                long.setdefault(name, []).append(int(number))
        if attempt == 0:
            for name, numbers in long.items():
                wrap_docstring_lines(repo.root / name, numbers)
    manual += [f"line too long, wrap it: {line}" for line in out.splitlines() if "E501" in line]


WIDTH = 100
#: A line that starts something: an item, a list entry, a directive, a blank, closing quotes.
ITEM = re.compile(r"^\s*(\*{0,2}\w+( \(.*\))?:(\s|$)|[-*] |\.\. |>>>|\"\"\"|'''|$)")
QUOTES = ('"""', "'''")


def _docstring_lines(text: str) -> set[int]:
    """1-based numbers of the lines inside triple-quoted strings."""
    inside = set()
    for tok in tokenize.generate_tokens(io.StringIO(text).readline):
        if tok.type == tokenize.STRING and tok.string.lstrip("rRbBuUfF")[:3] in QUOTES:
            inside.update(range(tok.start[0], tok.end[0] + 1))
    return inside


def wrap_docstring_lines(path: Path, numbers: list[int]) -> None:
    """Break each too-long docstring line at its last space before column 100. The rest goes to
    the start of the next line when that one continues the same paragraph (same indent, not an
    item, a list entry, a directive, a blank or the closing quotes), else onto a new line (at the
    next line's indent when that is a hanging continuation, else at this line's)."""
    text = path.read_text(encoding="utf-8")
    inside = _docstring_lines(text)
    lines = text.split("\n")
    for number in sorted(numbers, reverse=True):
        i = number - 1
        while number in inside and i < len(lines) and len(lines[i]) > WIDTH:
            line = lines[i]
            indent = len(line) - len(line.lstrip())
            cut = line.rfind(" ", indent + 4, WIDTH + 1)
            if cut < 0:
                break
            head, tail = line[:cut].rstrip(), line[cut + 1 :]
            nxt = lines[i + 1] if i + 1 < len(lines) else ""
            n_indent = len(nxt) - len(nxt.lstrip())
            opening = line.lstrip().lstrip("rR").startswith(QUOTES)
            cont = n_indent if nxt.strip() and n_indent > indent and not opening else indent
            if nxt.strip() and n_indent == cont and not ITEM.match(nxt) and '"""' not in tail:
                lines[i], lines[i + 1] = head, " " * cont + tail + " " + nxt.lstrip()
            else:
                lines[i] = head
                lines.insert(i + 1, " " * cont + tail)
            i += 1
    path.write_text("\n".join(lines), encoding="utf-8")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--root", type=Path, default=Path.cwd(), help="repository root (default: .)")
    p.add_argument("--dry-run", action="store_true", help="print what would change, change nothing")
    p.add_argument("--check", action="store_true", help="like --dry-run; exit 1 if work is left")
    args = p.parse_args(argv)
    repo = Repo(args.root.resolve(), args.dry_run or args.check)
    if not (repo.root / "pigp_torch").is_dir():
        p.error(f"{repo.root} is not the repository root (no pigp_torch/)")
    manual = move(repo)
    if repo.dry and repo.changes:
        print("(the rewrite below reads the files where they are now)")
    rewrite(repo, manual)
    layers(repo, manual)
    if repo.rewritten and not repo.dry:
        tidy(repo, manual)
    top = sorted(c.name for c in (repo.root / "pigp_torch").iterdir() if c.name != "__pycache__")
    print(f"{repo.changes} change(s); pigp_torch/ top level: {', '.join(top)}")
    for line in manual:
        print(f"CHECK BY HAND: {line}")
    return 1 if args.check and repo.changes else 0


if __name__ == "__main__":
    sys.exit(main())
