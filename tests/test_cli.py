"""The pigp command: help texts, train-surrogate -> build-prior on tiny data, benchmark output."""

import json

import pytest
import torch

from pigp_torch.cli import build_parser, main
from pigp_torch.data.tables import read_table
from pigp_torch.prior import PhysicsPrior, log_excess_hessian
from pigp_torch.surrogate import load_surrogate


def test_every_command_documents_itself(capsys):
    """`pigp --help` lists every subcommand and each has its own help text."""
    parser = build_parser()
    with pytest.raises(SystemExit):
        parser.parse_args(["--help"])
    text = capsys.readouterr().out
    for cmd in ("generate-data", "train-surrogate", "build-prior", "bench"):
        assert cmd in text
        with pytest.raises(SystemExit):
            parser.parse_args([cmd, "--help"])
        assert "usage: pigp" in capsys.readouterr().out


def test_data_surrogate_prior_chain(tmp_path, capsys):
    """generate-data -> train-surrogate -> build-prior: the prior's precision is -H/2 of the
    surrogate's log-excess at the prior's x0, with provenance back to the model ring."""
    data, model, prior = tmp_path / "d.npz", tmp_path / "m.pt", tmp_path / "p.json"
    assert main(["generate-data", "--seed", "3", "--n", "6000", "-o", str(data)]) == 0
    argv = [str(data), "-o", str(model), "--epochs", "40", "--members", "2", "--quiet"]
    argv += ["--target", "log_excess"]  # bounded f̂: an under-trained net has no spurious peak
    assert main(["train-surrogate", *argv]) == 0
    assert main(["build-prior", str(model), "-o", str(prior), "--starts", "2"]) == 0
    p = PhysicsPrior.load(prior)
    surrogate, meta = load_surrogate(model)
    H, _, _ = log_excess_hessian(surrogate, p.x0, p.f_inf)
    # precision = -H/2 up to the negative-definite repair the prior reports (tiny net, few data)
    rel = float(torch.linalg.norm(p.precision + H / 2) / torch.linalg.norm(H / 2))
    assert rel <= p.provenance["build"]["repair_relative_change"] + 1e-9
    assert p.knob_names == meta["knob_names"] and p.noise == 0.04
    assert p.provenance["model_error_seed"] == 3
    assert "saved prior" in capsys.readouterr().out


def test_bench_simulator_json(capsys):
    """`pigp bench simulator --json` prints one JSON object with throughputs and agreement."""
    assert main(["bench", "simulator", "--batch", "500", "--n-reference", "1", "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["fast"]["cpu"]["samples_per_s"] > 0
    assert res["speedup_cpu_vs_reference"] > 1
    assert res["max_rel_diff"]["loss_rate"] < 1e-4


def test_compare_writes_tables_and_figures(tmp_path, capsys):
    """`pigp compare` on one machine with tiny budgets writes runs, summary and the figures."""
    out = tmp_path / "cmp"
    argv = ["compare", "--methods", "pigp", "pigp-zero-mean", "nelder-mead", "--seeds", "1"]
    argv += ["--budget-gp", "4", "--budget-direct", "5", "--prior-source", "exact", "-o", str(out)]
    assert main(argv) == 0

    runs = read_table(out / "runs.csv")
    assert len(runs) == 4 + 4 + 5
    header = (out / "runs.csv").read_text().splitlines()[0].split(",")  # every unit in it
    assert {"y [mA/min]", "best_f_true [mA/min]", "f_star [mA/min]", "01G-QSS4 [A]"} <= set(header)
    assert {"step", "method", "gain_fraction", "ask_time_s"} <= set(header)
    summary = (out / "summary.csv").read_text().splitlines()[0].split(",")
    assert {"best_f_true_median [mA/min]", "steps_to_95_median [evaluations]"} <= set(summary)
    assert set(runs["method"]) == {"pigp", "pigp-zero-mean", "nelder-mead"}
    for name in ("summary.csv", "fig2b_runs.png", "fig2c_prior_mean.png"):
        assert (out / name).stat().st_size > 0
    assert "nelder-mead" in capsys.readouterr().out


def test_demo_small(tmp_path):
    """`pigp demo` end to end at toy size: the three methods run on the machine, prior saved."""
    out = tmp_path / "demo"
    argv = ["demo", "--n", "3000", "--members", "1", "--budget", "4", "--target", "log_excess"]
    argv += ["--center-ensemble", "0"]  # the ensemble (~50 s) is covered by a slow test
    assert main([*argv, "-o", str(out)]) == 0

    runs = read_table(out / "runs.csv")
    assert sorted(set(runs["method"])) == ["ml2", "pigp", "pigp-physics"] and len(runs) == 12
    assert (runs["machine_seed"] == 1).all()
    assert PhysicsPrior.load(out / "prior.json").provenance["surrogate_of"].endswith("=0)")
    with pytest.raises(SystemExit):
        build_parser().parse_args(["demo", "--target"])


def test_demo_refuses_unknown_method(capsys):
    assert main(["demo", "--methods", "pigp", "no-such-method"]) == 2
    assert "unknown method(s) ['no-such-method']" in capsys.readouterr().err


def test_demo_refuses_same_seed(capsys):
    """The model ring must differ from the machine (the prior must not know the machine)."""
    assert main(["demo", "--model-seed", "3", "--machine-seed", "3"]) == 2
    assert "different error seeds" in capsys.readouterr().err


def test_demo_refuses_a_machine_among_the_ensemble_rings(capsys):
    """The rings that give the centre prior must not include the machine under test."""
    assert main(["demo", "--machine-seed", "1002", "--center-ensemble", "20"]) == 2
    assert "choose model and machine seeds outside them" in capsys.readouterr().err


def test_a_too_small_center_ensemble_is_refused_before_any_ring(capsys, monkeypatch):
    """Fewer ensemble rings than knobs + 1 is refused at once (no ring is built), and --help says
    the minimum."""
    import pigp_torch.machines.ring.ensemble as ens

    def no_rings(*a, **k):
        raise AssertionError("a ring was computed")

    monkeypatch.setattr(ens, "ensemble_optima", no_rings)
    for argv in (["demo", "--center-ensemble", "13"],
                 ["compare", "--center-ensemble", "5", "--seeds", "1"]):  # fmt: skip
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert "too small for 13 knobs" in err and "at least 14" in err
    for cmd in ("demo", "compare", "build-prior"):
        with pytest.raises(SystemExit):
            main([cmd, "--help"])
        assert "at least 14" in " ".join(capsys.readouterr().out.split())


@pytest.mark.slow
def test_demo_with_center_ensemble(tmp_path):
    """`pigp demo --center-ensemble 14`: the saved prior carries the 13 x 13 covariance of the
    optima of rings 1001-1014 and their mean peak shape, and pigp-physics ran with them (~60 s)."""
    out = tmp_path / "demo"
    argv = ["demo", "--n", "3000", "--members", "1", "--budget", "4", "--target", "log_excess"]
    argv += ["--methods", "pigp-physics", "--center-ensemble", "14", "-o", str(out)]
    assert main(argv) == 0
    p = PhysicsPrior.load(out / "prior.json")
    assert p.center_cov.shape == (13, 13)
    assert p.provenance["center_ensemble_seeds"] == [1001, 1014, 14]
    assert torch.linalg.eigvalsh(p.center_cov).min() > 0
    assert p.peak_shape.shape == (13, 13) and torch.linalg.eigvalsh(p.peak_shape).min() > 0


def test_demo_cache_gives_the_same_prior_and_runs(tmp_path, capsys):
    """A second `pigp demo` reads the surrogate's prior from the cache and gives the same prior
    file and the same runs; --no-cache reads and writes nothing."""
    argv = ["demo", "--n", "2000", "--members", "1", "--budget", "3", "--target", "log_excess"]
    argv += ["--methods", "pigp-physics", "--center-ensemble", "0"]
    cache = ["--cache-dir", str(tmp_path / "cache")]
    assert main([*argv, *cache, "-o", str(tmp_path / "a")]) == 0
    first = capsys.readouterr().out
    assert "[1/4]" in first and "from the cache" not in first
    assert "pigp-physics  evaluation    3/3" in first  # a progress line per evaluation
    assert len(list((tmp_path / "cache").glob("prior-*.json"))) == 1
    assert main([*argv, *cache, "-o", str(tmp_path / "b")]) == 0
    second = capsys.readouterr().out
    assert "[1/4]" not in second and "from the cache" in second
    assert (tmp_path / "a/prior.json").read_bytes() == (tmp_path / "b/prior.json").read_bytes()
    import pandas as pd

    a, b = (read_table(tmp_path / x / "runs.csv") for x in "ab")
    numbers = [c for c in a.columns if not c.endswith("_time_s")]  # timings differ, not numbers
    pd.testing.assert_frame_equal(a[numbers], b[numbers], check_exact=True)
    assert main([*argv, *cache, "--no-cache", "-o", str(tmp_path / "c")]) == 0
    assert "[1/4]" in capsys.readouterr().out
    assert (tmp_path / "a" / "prior.json").read_bytes() == (
        tmp_path / "c" / "prior.json"
    ).read_bytes()
    assert len(list((tmp_path / "cache").glob("*.json"))) == 1


def test_the_ensemble_cache_stores_what_it_was_given(tmp_path):
    """with_cached_ensemble: computed once, then read back bit for bit (keyed by seed, size)."""
    import dataclasses

    from pigp_torch.bench.demo_cache import DemoCache, with_cached_ensemble

    d = 3
    prior = PhysicsPrior(
        x0=torch.zeros(d, dtype=torch.float64), f_x0=1.0, f_inf=0.2,
        precision=torch.eye(d, dtype=torch.float64), amplitude=0.1, noise=0.04,
        knob_names=["a", "b", "c"], bounds=torch.tensor([[-1.0] * d, [1.0] * d]),
    )  # fmt: skip
    cov = torch.tensor([[2.0, 0.1, 0.0], [0.1, 1.0 / 3, 0.0], [0.0, 0.0, 0.7]])
    calls = []

    def compute(p):
        calls.append(1)
        prov = {**p.provenance, "center_ensemble_seeds": [1001, 1020, 20]}
        return dataclasses.replace(p, center_cov=cov, peak_shape=2 * cov, provenance=prov)

    cache = DemoCache(tmp_path)
    a, source_a = with_cached_ensemble(prior, 20, 0, cache, compute)
    b, source_b = with_cached_ensemble(prior, 20, 0, cache, compute)
    assert calls == [1] and source_a is None and source_b.is_file()
    assert torch.equal(a.center_cov, b.center_cov) and torch.equal(a.peak_shape, b.peak_shape)
    assert b.provenance["center_ensemble_seeds"] == [1001, 1020, 20]
    with_cached_ensemble(prior, 21, 0, cache, compute)  # another size: computed again
    assert calls == [1, 1]


def test_help_names_every_default():
    """Every option of every command that has a default names it in --help, once: a help text
    that already gives its default in words gets no second '(default: ...)'."""
    import argparse

    from pigp_torch.cli import build_parser

    def parsers(p, path):
        yield path, p
        for a in p._actions:
            if isinstance(a, argparse._SubParsersAction):
                for name, child in a.choices.items():
                    yield from parsers(child, [*path, name])

    checked = 0
    for path, p in parsers(build_parser(), ["pigp"]):
        formatter = p._get_formatter()
        for a in p._actions:
            if not a.option_strings or a.help is argparse.SUPPRESS:
                continue
            if any(a.default is v for v in (None, False, argparse.SUPPRESS)):
                continue
            text = formatter._expand_help(a)
            assert "default" in text.lower(), (path, a.option_strings)
            assert text.lower().count("default") == 1 or "(default:" not in text, text
            checked += 1
    assert checked > 60
    text = " ".join(build_parser()._subparsers._group_actions[0].choices["train-surrogate"]
                    .format_help().split())  # fmt: skip
    assert "--batch-size BATCH_SIZE (default: 1024)" in text
    assert "networks averaged (default 3) " in text and "(default: 3)" not in text


def test_summary_table_fits_100_columns():
    """The printed summary: one row per method, every line within 100 characters, units named."""
    import math

    import pandas as pd

    from pigp_torch.commands.compare import format_summary

    cols = {"n_runs": 24, "n_reached_95": 20, "budget": 100, "steps_to_95_median": 31.5,
            "steps_to_95_q25": 22.0, "steps_to_95_q75": 48.25, "gain_20_median": 0.81234,
            "gain_40_median": 0.95, "gain_100_median": math.nan, "best_f_true_median": 1.69871,
            "ask_time_s_median": 0.2134}  # fmt: skip
    table = pd.DataFrame([cols, cols], index=pd.Index(["pigp-physics-box-long-name", "ml2"],
                                                       name="method"))  # fmt: skip
    lines = format_summary(table).splitlines()
    assert max(len(ln) for ln in lines) <= 100
    assert "mA/min" in lines[1] and lines[2].startswith("pigp-physics-box ")
    row = lines[3].split()
    assert row == ["ml2", "24", "20/24", "32", "[22-48]", "0.812", "0.950", "-", "1.6987", "0.213"]
    table.loc["ml2", "steps_to_95_median"] = 101.0  # the median run did not reach 95 %
    assert format_summary(table).splitlines()[3].split()[3] == ">100"


@pytest.mark.slow
def test_demo_on_two_processes_gives_the_numbers_of_one(tmp_path):
    """`pigp demo --workers 2` (networks, ensemble rings and runs shared with a spawned process)
    writes the same prior file, byte for byte, and the same runs as `--workers 1`."""
    import pandas as pd

    argv = ["demo", "--n", "3000", "--members", "2", "--budget", "4", "--target", "log_excess"]
    argv += ["--methods", "pigp-physics", "ml2", "--center-ensemble", "14", "--no-cache"]
    for w in (1, 2):
        assert main([*argv, "--workers", str(w), "-o", str(tmp_path / f"w{w}")]) == 0
    one, two = tmp_path / "w1", tmp_path / "w2"
    assert (one / "prior.json").read_bytes() == (two / "prior.json").read_bytes()
    a, b = read_table(one / "runs.csv"), read_table(two / "runs.csv")
    timing = [c for c in a.columns if c.endswith("_time_s")]
    assert len(a) == 8 and set(timing) == {"ask_time_s", "eval_time_s"}
    pd.testing.assert_frame_equal(a.drop(columns=timing), b.drop(columns=timing))
