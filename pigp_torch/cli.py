"""The ``pigp`` command: data generation, surrogate training, priors, optimization, benchmarks.

Run ``pigp --help`` or ``pigp COMMAND --help``. Each command lives in its own module of
:mod:`pigp_torch.commands` (listed in :data:`COMMAND_MODULES`, in the order of the help); this
module only wires the parser. Heavy imports happen inside each command so that ``pigp --help``
answers at once.
"""

from __future__ import annotations

import os

# The simulator multiplies many stacks of 6x6 matrices with numpy; a multi-threaded OpenBLAS makes
# them much slower on a busy machine. Must be set before numpy is first imported.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import importlib
import sys

from pigp_torch.commands.compare import seed_list as _seed_list  # noqa: F401  (benchmarks/ use it)

#: Modules of ``pigp_torch.commands``, each with ``register(sub, bench)`` adding its sub-parsers.
#: ``kinds`` adds each machine kind's commands (the ring's ``generate-data``, ``compare``,
#: ``demo``, ``serve-sim``, ``bench simulator``, ``bench spear3``; ARES-EA's ``bench ares``).
COMMAND_MODULES: tuple[str, ...] = (
    "kinds",
    "train_surrogate",
    "build_prior",
    "optimize",
    "badger_setup",
    "bench_bo",
    "report",
)


class _BenchCommands:
    """The sub-parsers of ``pigp bench``, created at the first bench command registered (so that
    ``bench`` is listed in the help where its first command's module stands)."""

    def __init__(self, sub) -> None:
        self._sub = sub
        self._bench = None

    def add_parser(self, *args, **kwargs) -> argparse.ArgumentParser:
        if self._bench is None:
            p = self._sub.add_parser("bench", help="benchmarks: the machine kinds' tasks, speeds")
            self._bench = p.add_subparsers(dest="bench", required=True)
        return self._bench.add_parser(*args, **kwargs)


class DefaultsHelpFormatter(argparse.HelpFormatter):
    """Help that shows every option's default: ``(default: X)`` is appended to an option's help
    unless the help already names its default (the word "default") or there is none to show (a
    flag, ``None``, a positional argument). ``argparse.ArgumentDefaultsHelpFormatter`` would
    repeat the defaults that the help strings already give in words."""

    def _get_help_string(self, action) -> str:
        text = action.help or ""
        shown = not any(action.default is v for v in (None, False, argparse.SUPPRESS))
        if not action.option_strings or not shown or "default" in text.lower():
            return text
        return f"{text} (default: %(default)s)".strip()


class RawDefaultsHelpFormatter(DefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """:class:`DefaultsHelpFormatter` that keeps the description and epilog as written."""


def _with_defaults(parser: argparse.ArgumentParser) -> None:
    """Give ``parser`` and its sub-parsers (recursively) the formatters that show defaults."""
    if parser.formatter_class is argparse.RawDescriptionHelpFormatter:
        parser.formatter_class = RawDefaultsHelpFormatter
    elif parser.formatter_class is argparse.HelpFormatter:
        parser.formatter_class = DefaultsHelpFormatter
    for action in parser._actions:
        if action.help is None and action.option_strings and action.default is not None:
            action.help = "(default: %(default)s)"  # argparse shows no help line without text
        if isinstance(action, argparse._SubParsersAction):
            for child in dict.fromkeys(action.choices.values()):
                _with_defaults(child)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="pigp",
        description="Physics-informed Gaussian-process optimization of particle accelerators.",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    bench = _BenchCommands(sub)
    for name in COMMAND_MODULES:
        importlib.import_module(f"pigp_torch.commands.{name}").register(sub, bench)
    _with_defaults(parser)
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (ValueError, FileNotFoundError, ConnectionError) as err:
        print(f"pigp {args.command}: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
