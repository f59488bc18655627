"""Tests of the benchmark protocol: seeds, table layout, noise-free scores, determinism."""

import numpy as np
import pandas as pd
import pytest
import torch

from pigp_torch.bench import METHODS, machine_archive, machine_optimum, run_benchmark, run_seed
from pigp_torch.machine import SimulatedMachine
from pigp_torch.methods import MethodSpec, resolve_methods
from pigp_torch.simulation import Spear3Coupling
from tests.benchmark.conftest import BUDGETS, MODEL_SEED, OPTIMUM_STARTS, SEEDS, tiny_methods

TIMING = ["ask_time_s", "eval_time_s"]


def test_model_seed_among_machine_seeds_raises():
    """The prior must come from a ring that is not under test: model_seed in seeds is refused."""
    with pytest.raises(ValueError, match="model_seed 2 is also a machine seed"):
        run_benchmark(["pigp"], [1, 2, 3], model_seed=2, progress=False)
    with pytest.raises(ValueError, match="duplicate machine seeds"):
        run_benchmark(["pigp"], [1, 1], progress=False)
    with pytest.raises(ValueError, match="unknown method"):
        run_benchmark(["no-such-method"], [1], progress=False)


def test_registry_and_spec_options():
    """The registry holds the five protocol methods; with_options overrides without mutating."""
    assert set(METHODS) >= {"pigp", "pigp-zero-mean", "ml2", "nelder-mead", "rcds"}
    spec = METHODS["pigp"].with_options(name="pigp-rq", kernel="rq", step_limit=0.1)
    assert (spec.name, dict(spec.options)) == ("pigp-rq", {"kernel": "rq", "step_limit": 0.1})
    assert dict(METHODS["pigp"].options) == {}
    assert METHODS["pigp-zero-mean"].options == {"mean": "zero"}
    assert (METHODS["ml2"].budget, METHODS["rcds"].budget) == ("gp", "direct")
    with pytest.raises(ValueError, match="duplicate method names"):
        resolve_methods(["pigp", METHODS["pigp"]])


def test_table_layout_one_row_per_evaluation(tiny_table):
    """One row per evaluation per run, steps 0..budget-1 in order, start at all skews zero."""
    names = Spear3Coupling(1).knob_names
    expected = ["method", "machine_seed", "step", *names, "y", *TIMING, "notice"]
    expected += ["f_true", "best_f_true", "f0", "f_star", "gain_fraction", "family"]
    assert list(tiny_table.columns) == expected
    counts = tiny_table.groupby(["method", "machine_seed"], sort=False).size()
    budgets = [BUDGETS["gp"]] * 6 + [BUDGETS["direct"]] * 4
    assert counts.tolist() == budgets
    assert [m for m, _ in counts.index[::2]] == [s.name for s in tiny_methods()]
    start = tiny_table[tiny_table["step"] == 0]
    assert (start[names].to_numpy() == 0.0).all()
    for _, run in tiny_table.groupby(["method", "machine_seed"]):
        assert run["step"].tolist() == list(range(len(run)))


def test_scores_are_noise_free(tiny_table):
    """f_true equals the machine's loss_rate (its own loss-rate map) at the logged knobs, f0 the
    skews-off value, and gain_fraction the best-so-far formula; y differs from f_true by the
    0.04 noise."""
    from pigp_torch.bench.protocol import benchmark_ring
    from pigp_torch.simulation.spec import SPEAR3

    for seed in SEEDS:
        sim = benchmark_ring(seed, SPEAR3)
        rows = tiny_table[tiny_table["machine_seed"] == seed]
        X = torch.tensor(rows[sim.knob_names].to_numpy(), dtype=torch.float64)
        f = sim.loss_rate(X).detach().numpy()
        assert rows["f_true"].to_numpy() == pytest.approx(f, rel=1e-12)
        f0 = float(sim.loss_rate(torch.zeros(1, 13, dtype=torch.float64))[0])
        assert rows["f0"].unique().tolist() == pytest.approx([f0], rel=1e-12)
        assert 0.3 < f0 < 0.7
        f_star = rows["f_star"].iloc[0]
        assert f_star == machine_optimum(seed, OPTIMUM_STARTS, machine_maps=True)
        assert f_star > rows["f_true"].max() > f0
        best = rows.groupby("method")["f_true"].cummax()
        assert rows["gain_fraction"].to_numpy() == pytest.approx((best - f0) / (f_star - f0))
    resid = (tiny_table["y"] - tiny_table["f_true"]).to_numpy()
    assert 0.02 < resid.std() < 0.06


def test_same_seeds_give_identical_table(tiny_table, tiny_prior):
    """A second run with the same seeds reproduces the table exactly (timings aside)."""
    again = run_benchmark(
        tiny_methods(),
        SEEDS,
        model_seed=MODEL_SEED,
        budgets=BUDGETS,
        archive_size=40,
        progress=False,
        prior=tiny_prior,
        optimum_starts=OPTIMUM_STARTS,
    )
    pd.testing.assert_frame_equal(tiny_table.drop(columns=TIMING), again.drop(columns=TIMING))


def test_run_seeds_differ_between_methods_and_machines():
    """Each run gets its own stable seed from (method, machine seed)."""
    seeds = {run_seed(m, s) for m in ("pigp", "ml2", "rcds") for s in (1, 2, 3)}
    assert len(seeds) == 9
    assert run_seed("pigp", 1) == run_seed("pigp", 1)


def test_machine_archive_is_near_operating_point():
    """Archive settings have the requested spread around zero (clipped) and 0.04 noise."""
    machine = SimulatedMachine(Spear3Coupling(1), noise=0.04, seed=0)
    X, Y = machine_archive(machine, 400, spread=0.2, seed=3)
    assert X.shape == (400, 13) and Y.shape == (400,)
    assert X.std().item() == pytest.approx(0.2 * 30.0, rel=0.1)  # amps
    assert X.abs().max().item() <= 30.0
    assert (Y - machine.true_value(X)).std().item() == pytest.approx(0.04, rel=0.15)
    assert machine.n_reads == 0


@pytest.mark.slow
def test_process_pool_gives_the_same_numbers(tiny_table, tiny_prior):
    """n_workers=2 reproduces the serial table (each run is seeded on its own)."""
    pooled = run_benchmark(
        tiny_methods(),
        SEEDS,
        model_seed=MODEL_SEED,
        budgets=BUDGETS,
        archive_size=40,
        progress=False,
        prior=tiny_prior,
        optimum_starts=OPTIMUM_STARTS,
        n_workers=2,
    )
    pd.testing.assert_frame_equal(tiny_table.drop(columns=TIMING), pooled.drop(columns=TIMING))


def test_a_run_uses_float64_defaults_whatever_the_caller_set(tiny_prior):
    """``import xopt`` switches torch's default dtype to float64 process-wide; a run pins it to
    float64 itself (so a Dask worker and a process that imported Xopt propose the same points)
    and gives the caller's default back afterwards."""
    from pigp_torch.bench import run_one

    seen = []
    pigp = METHODS["pigp"].with_options(num_restarts=2, raw_samples=32)

    def build(ctx, **options):
        seen.append(torch.get_default_dtype())
        return pigp.build(ctx)

    spec = MethodSpec("pigp", build, "gp")  # same name, so the same run seed as ``pigp``
    tables = []
    saved = torch.get_default_dtype()
    try:
        for dtype in (torch.float32, torch.float64):
            torch.set_default_dtype(dtype)
            tables.append(run_one(spec, 1, tiny_prior, budget=5, optimum_starts=OPTIMUM_STARTS))
            assert torch.get_default_dtype() == dtype
    finally:
        torch.set_default_dtype(saved)
    assert seen == [torch.float64, torch.float64]
    timing = ["ask_time_s", "eval_time_s"]
    pd.testing.assert_frame_equal(tables[0].drop(columns=timing), tables[1].drop(columns=timing))


def test_each_machine_has_its_own_loss_rate_map():
    """A machine's map is drawn from its seed (same in every call), within the protocol's spread
    of the model's constants; the prior's model ring keeps the model's."""
    from pigp_torch.bench.protocol import MAP_SPREAD, benchmark_ring, machine_loss_map
    from pigp_torch.simulation import LOSS_RATE_MAP
    from pigp_torch.simulation.spec import SPEAR3

    maps = [machine_loss_map(s, LOSS_RATE_MAP) for s in range(1, 25)]
    assert maps[0] == machine_loss_map(1, LOSS_RATE_MAP)
    d = np.array([m[0] / LOSS_RATE_MAP[0] - 1 for m in maps])
    e = np.array([m[1] / LOSS_RATE_MAP[1] - 1 for m in maps])
    lo, hi = MAP_SPREAD["background"]
    assert (d >= lo).all() and (d <= hi).all() and d.std() > 0.2
    lo, hi = MAP_SPREAD["touschek"]
    assert (e >= lo).all() and (e <= hi).all() and e.std() > 0.1
    machine = benchmark_ring(1, SPEAR3)
    assert machine.loss_rate_map == maps[0]
    assert benchmark_ring(1, SPEAR3, machine_maps=False).loss_rate_map == LOSS_RATE_MAP
    # factors of the model's map, the same for every machine (the mismatch suite's machines)
    for seed in (1, 2):
        f_inf, g = benchmark_ring(seed, SPEAR3, machine_maps=(1.6, 0.5)).loss_rate_map
        assert f_inf == pytest.approx(1.6 * LOSS_RATE_MAP[0], rel=1e-12)
        assert g == pytest.approx(0.5 * LOSS_RATE_MAP[1], rel=1e-12)
    assert benchmark_ring(1, SPEAR3, machine_maps=(0.0, 1.0)).loss_rate_map[0] == 0.0
    with pytest.raises(ValueError, match="loss-map factors"):
        benchmark_ring(1, SPEAR3, machine_maps=(1.0, 0.0))
