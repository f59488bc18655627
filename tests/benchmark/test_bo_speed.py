"""Tests of the BO step-time benchmark (tiny sizes, no timing assertions) and `pigp bench bo`."""

from __future__ import annotations

import argparse
import json
from types import SimpleNamespace

import pytest
import torch

from pigp_torch.bench import BO_DEFAULTS
from pigp_torch.bench.bo_speed import (
    bo_step_times,
    build_pigp_fast,
    format_table,
    synthetic_problem,
)
from pigp_torch.commands import bench_bo
from pigp_torch.optimizers.fast_bo import FastBayesOpt

PATHS = ("fast", "stock", "ml2")


@pytest.fixture(scope="module")
def tiny_result():
    return bo_step_times(ns=(3, 6), dims=(2,), repeats=2, stock_repeats=1, ml2_max_n=3)


def test_result_has_documented_keys_and_consistent_ratios(tiny_result):
    """One row per (d, n) with median/p90 per path; ratios are stock / fast; ML-II skipped above
    ml2_max_n; the fast proposal is at least as good as the stock one on the same data."""
    assert tiny_result["config"]["ns"] == [3, 6] and tiny_result["config"]["dims"] == [2]
    assert tiny_result["config"]["stock"]["num_restarts"] == 10
    assert tiny_result["config"]["stock"]["raw_samples"] == 256
    rows = tiny_result["results"]
    assert [(r["d"], r["n"]) for r in rows] == [(2, 3), (2, 6)]
    for r in rows:
        assert r["fast"]["n_steps"] == 2 and r["stock"]["n_steps"] == 1
        for path in ("fast", "stock"):
            q = r[path]
            assert 0 < q["median_ms"] <= q["p90_ms"]
            assert 0 < q["cpu_median_ms"] <= q["cpu_p90_ms"]
        assert r["speedup_median"] == pytest.approx(
            r["stock"]["median_ms"] / r["fast"]["median_ms"]
        )
        assert r["speedup_p90"] == pytest.approx(r["stock"]["p90_ms"] / r["fast"]["p90_ms"])
        assert r["fast_solver"] == "newton"
        assert r["acq_gap"] <= 1e-6
    assert rows[0]["ml2"]["n_steps"] == 1 and rows[1]["ml2"] is None
    json.dumps(tiny_result)  # plain data


def test_format_table_lists_every_row(tiny_result):
    """The readable table has a header, one line per (d, n) and the legend."""
    lines = format_table(tiny_result).splitlines()
    assert lines[1].split()[:2] == ["d", "n"]
    assert [line.split()[:2] for line in lines[2:4]] == [["2", "3"], ["2", "6"]]
    assert lines[2].split()[-1] == "newton"
    assert lines[3].split("|")[4].split() == ["-", "-", "-"]  # ML-II skipped above ml2_max_n
    assert "acq gap" in lines[-1]


def test_bad_arguments_raise():
    with pytest.raises(ValueError, match="positive integers"):
        bo_step_times(ns=(0,), dims=(2,))
    with pytest.raises(ValueError, match="repeats must be >= 1"):
        bo_step_times(ns=(2,), dims=(2,), repeats=0)


def test_synthetic_problem_peak_and_conditioning():
    """The test problem peaks at x0 with 1.7, background 0.2, precision condition number 483."""
    prior, f, bounds = synthetic_problem(13, 0)
    assert float(f(prior.x0[None])[0]) == pytest.approx(1.7, abs=1e-12)
    assert float(f(bounds[1][None] * 50)[0]) == pytest.approx(0.2, abs=1e-9)
    eig = torch.linalg.eigvalsh(prior.precision)
    assert float(eig.max() / eig.min()) == pytest.approx(483.0, rel=1e-8)
    assert (prior.x0.abs() <= bounds[1] / 2).all()


def test_build_pigp_fast_uses_bo_defaults():
    """The benchmark builder takes the PI-GP prior and the BO defaults of the 'pigp' method."""
    prior, _, bounds = synthetic_problem(3, 0)
    ctx = SimpleNamespace(bounds=bounds, prior=prior, seed=17)
    opt = build_pigp_fast(ctx, beta=2.0)
    assert isinstance(opt, FastBayesOpt)
    assert opt.step_limit == BO_DEFAULTS["step_limit"] and opt.beta == 2.0
    assert opt.seed == 17 and opt.gp.mean_const == prior.f_inf


def test_cli_bench_bo_json(capsys):
    """`pigp bench bo --json` (registered on a fresh parser) prints one JSON object."""
    parser = argparse.ArgumentParser(prog="pigp")
    sub = parser.add_subparsers(dest="command", required=True)
    bench = sub.add_parser("bench").add_subparsers(dest="bench", required=True)
    bench_bo.register(sub, bench)
    args = parser.parse_args(
        [
            "bench",
            "bo",
            "--json",
            "--quiet",
            "--ns",
            "3",
            "--dims",
            "2",
            "--repeats",
            "1",
            "--no-ml2",
        ]
    )
    assert args.func(args) == 0
    out = json.loads(capsys.readouterr().out)
    assert [(r["d"], r["n"], r["ml2"]) for r in out["results"]] == [(2, 3, None)]
    args = parser.parse_args(["bench", "bo", "--ns", "3", "--dims", "2", "--repeats", "1"])
    assert args.func(args) == 0
    assert "stock / fast" in capsys.readouterr().out  # the table's header
    with pytest.raises(SystemExit):
        parser.parse_args(["bench", "bo", "--ns", "ten"])
