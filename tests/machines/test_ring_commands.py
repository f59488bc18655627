"""The ring kind brings its ``pigp`` commands (its folder's
:mod:`pigp_torch.machines.ring.commands`, added through the registry): ``pigp bench spear3`` is
``pigp compare`` under the kind's bench name, and the old module paths of the moved commands are the
moved modules."""

from __future__ import annotations

import argparse
import importlib

import pytest

from pigp_torch.cli import build_parser
from pigp_torch.machines import KINDS

RING_COMMANDS = ("compare", "demo", "generate_data", "serve_sim", "bench_simulator", "ring_options")


def _subcommands(parser) -> dict:
    return parser._subparsers._group_actions[0].choices


def test_bench_spear3_is_compare_with_the_same_options_and_defaults():
    parser = build_parser()
    argv = ["--methods", "pigp-physics", "rcds", "--seeds", "1", "--budget-gp", "8"]
    a = parser.parse_args(["compare", *argv])
    b = parser.parse_args(["bench", "spear3", *argv])
    assert a.func is b.func and a.func.__name__ == "cmd_compare"
    a, b = vars(a), vars(b)
    assert a.pop("command") == "compare" and b.pop("command") == "bench"
    assert b.pop("bench") == "spear3"
    assert a == b and a["seeds"] == "1" and a["budget_gp"] == 8 and a["budget_direct"] == 300
    compare = _subcommands(parser)["compare"]
    spear3 = _subcommands(_subcommands(parser)["bench"])["spear3"]
    options = [sorted(x.option_strings) for x in compare._actions]
    assert options == [sorted(x.option_strings) for x in spear3._actions]
    assert len(options) > 15


def test_the_commands_come_from_the_kinds():
    """Every top-level command and ``bench`` command of a kind is there, from that kind; the
    ring's are exactly its six (four top-level, two under ``bench``)."""

    class Collect:
        def __init__(self):
            self.names = []

        def add_parser(self, name, **kwargs):
            self.names.append(name)
            return argparse.ArgumentParser(prog=name)

    top, bench = Collect(), Collect()
    KINDS["spear3"].register_commands(top)
    KINDS["spear3"].register_bench(bench)
    assert top.names == ["generate-data", "compare", "demo", "serve-sim"]
    assert bench.names == ["simulator", "spear3"]
    parser = build_parser()
    assert set(top.names) <= set(_subcommands(parser))
    assert {"ares", "simulator", "spear3", "bo"} == set(_subcommands(_subcommands(parser)["bench"]))


@pytest.mark.parametrize("name", RING_COMMANDS)
def test_a_moved_command_keeps_its_old_path_as_the_same_module(name):
    old = importlib.import_module(f"pigp_torch.commands.{name}")
    assert old is importlib.import_module(f"pigp_torch.machines.ring.commands.{name}")
    assert old.__spec__.name == f"pigp_torch.machines.ring.commands.{name}"


def _ring_run(**machine):
    from pathlib import Path

    from pigp_torch.loop.config import parse_config, read_run_file

    root = Path(__file__).resolve().parents[2]
    data = read_run_file(root / "examples" / "run_sim.yaml")
    data["machine"].update(machine)
    return parse_config(data, base_dir=root / "examples")


def test_the_plan_text_of_a_simulated_ring_comes_from_the_kind():
    """``pigp optimize --dry-run`` names the simulated machine in its kind's words: the ring's
    deck or lattice, error seed, loss-rate map, noise in the run's objective unit, noise seed."""
    ring = KINDS["spear3"]
    config = _ring_run(error_seed=3, noise=0.02, seed=5, loss_map="benchmark")
    assert ring.describe(config, None) == (
        "simulated ring (SPEAR3 user, error seed 3 with the benchmark's loss-rate map, noise "
        "0.02 mA/min, noise seed 5)"
    )
    config = _ring_run(optics="design")
    config.objective_unit = "m"  # a length is shown in µm, as every number of the plan
    assert "(SPEAR3 design, error seed 1 with the ring's loss-rate map" in ring.describe(config, 0)
    assert ring.describe(config, None).endswith("noise 40000 µm, noise seed 0)")


def test_an_ask_time_of_eight_characters_stays_a_column_of_its_own():
    """``7.82e-05`` s (8 characters, an RCDS proposal) does not run into the best loss rate; a
    shorter time keeps the column where it was (the table's width is unchanged)."""
    import pandas as pd

    from pigp_torch.machines.ring.commands.compare import format_summary

    row = {"n_runs": 1, "n_reached_95": 0, "budget": 6, "steps_to_95_median": float("nan"),
           "best_f_true_median": 0.6154, "ask_time_s_median": 7.82e-05}  # fmt: skip
    table = pd.DataFrame([row, {**row, "ask_time_s_median": 0.0459}],
                         index=pd.Index(["rcds", "pigp-physics"], name="method"))  # fmt: skip
    fast, slow = format_summary(table).splitlines()[2:4]
    assert fast.split()[-2:] == ["0.6154", "7.82e-05"]
    assert slow.endswith("    0.6154  0.0459") and len(slow) == len(fast) - 1
