"""The optimization loop driving EpicsMachine over Channel Access: a run, and faults during runs."""

import math
import warnings

import pytest
import torch

from pigp_torch import optimize
from pigp_torch.machine.epics import EpicsMachine
from pigp_torch.machine.errors import MachineError, ReadbackError, ReadError
from pigp_torch.optimizers import NelderMead

from .conftest import FAST, IOC_SEED, NOISE, UPDATE_PERIOD


def machine(handle, bounds, **options):
    return EpicsMachine(handle.knob_names, bounds, handle.loss_rate_pv, **{**FAST, **options})


def start_point(d: int) -> torch.Tensor:
    """The knobs found at the start of a run (nonzero, so that a restore is visible)."""
    return torch.full((d,), 0.002, dtype=torch.float64)


def run_with_fault(handle, probe, ring, fault, *, budget=6, fault_after=1, **options):
    """Run Nelder-Mead from start_point; ``fault(probe)`` fires after step ``fault_after``."""
    x_start = start_point(len(handle.knob_names))
    probe.write_many(handle.setpoint_pvs, x_start)
    rows = []

    def callback(row):
        rows.append(row)
        if row["step"] == fault_after:
            fault(probe)

    with machine(handle, ring.bounds, **options) as m:
        optimizer = NelderMead(ring.bounds, initial_simplex_size=0.05)
        try:
            optimize(m, optimizer, budget=budget, callback=callback)
        except BaseException as err:
            return rows, err, m, x_start
    return rows, None, m, x_start


def test_nan_readings_fewer_than_retries_run_continues(ioc, probe, ring):
    """read_retries NaN readings in a row: the run finishes with finite readings."""
    rows, err, m, x_start = run_with_fault(
        ioc, probe, ring, lambda p: p.write(ioc.nan_readings_pv, 2), budget=4, read_retries=2
    )
    assert err is None
    assert [r["step"] for r in rows] == [0, 1, 2, 3]
    assert all(math.isfinite(r["y"]) for r in rows)
    assert m.n_invalid_readings == 2
    # restore="initial": the knobs are back where the run found them
    assert torch.equal(probe.read_many(ioc.setpoint_pvs), x_start)


def test_nan_readings_more_than_retries_raise_and_restore(ioc, probe, ring):
    """NaN readings beyond every retry: ReadError, and the initial knobs are set back.

    (The loop may retry a failed ``read()`` on its own; 100 NaN readings outlast both layers.)
    """
    rows, err, m, x_start = run_with_fault(
        ioc, probe, ring, lambda p: p.write(ioc.nan_readings_pv, 100), read_retries=2
    )
    assert isinstance(err, ReadError)
    assert "in 3 attempts: non-finite value nan" in str(err)  # the machine's own message
    assert m.n_reads == 2 and m.n_invalid_readings >= 3
    assert [r["step"] for r in rows] == [0, 1]  # steps before the fault are logged
    assert not torch.equal(torch.tensor([rows[1][n] for n in ioc.knob_names]), x_start)
    assert torch.equal(probe.read_many(ioc.setpoint_pvs), x_start)
    assert torch.equal(probe.read_many(ioc.readback_pvs), x_start)


def test_slow_readback_raises_and_restores_setpoints(ioc, probe, ring):
    """Readbacks slower than settle_time + timeout: ReadbackError, initial setpoints written."""
    with warnings.catch_warnings(record=True):  # the restore may also time out on its readback
        warnings.simplefilter("always")
        rows, err, _, x_start = run_with_fault(
            ioc,
            probe,
            ring,
            lambda p: p.write(ioc.readback_delay_pv, 0.8),
            settle_time=0.1,
            timeout=0.3,
        )
    assert isinstance(err, ReadbackError)
    assert [r["step"] for r in rows] == [0, 1]
    assert torch.equal(probe.read_many(ioc.setpoint_pvs), x_start)
    assert torch.equal(probe.wait_for(ioc.readback_pvs, x_start, timeout=3.0), x_start)


@pytest.mark.slow
def test_ioc_killed_mid_run(ring, tmp_path):
    """The IOC dies after step 2, just as step 3's puts go out: the loop raises MachineError;
    the completed rows are intact. The end record's last setpoint is the last one the IOC
    acknowledged — the values of the last puts in its own put log — not step 3's setting,
    which was intended (logged as an intent) but never reached it."""
    from pigp_torch.data.runlog import read_log
    from pigp_torch.simulated_epics.ioc import start_sim_ioc

    log = tmp_path / "r.jsonl"
    with start_sim_ioc(IOC_SEED, update_period=UPDATE_PERIOD) as handle:
        rows = []

        def callback(row):
            rows.append(row)

        with machine(handle, ring.bounds) as m:
            real_write = m._ca.write_many

            def write_many(*args, **kwargs):  # the IOC dies as step 3's puts are sent
                if len(rows) == 3:
                    handle.kill()
                return real_write(*args, **kwargs)

            m._ca.write_many = write_many
            optimizer = NelderMead(ring.bounds, initial_simplex_size=0.05)
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                with pytest.raises(MachineError):
                    optimize(m, optimizer, budget=8, callback=callback, log=log)
        assert not handle.alive()
        received = {p["knob"]: p["value"] for p in handle.puts()}
    assert [r["step"] for r in rows] == [0, 1, 2]
    X = torch.tensor([[r[n] for n in ring.knob_names] for r in rows], dtype=torch.float64)
    y = torch.tensor([r["y"] for r in rows], dtype=torch.float64)
    assert ((X >= ring.bounds[0]) & (X <= ring.bounds[1])).all()
    assert torch.isfinite(y).all()
    f_true = ring.loss_rate(X)
    assert ((y - f_true).abs() < 5 * NOISE).all()  # each logged reading belongs to its knobs
    assert any("could not restore" in str(w.message) for w in caught)  # nothing to restore to
    end = read_log(log).last_end
    assert end["restored"] is False
    held = [received.get(n, 0.0) for n in ring.knob_names]  # never put: its power-on 0 A
    assert end["last_setpoint"] == held == X[2].tolist()
    assert end["last_intended"] != end["last_setpoint"]  # step 3's setting never arrived


@pytest.mark.slow
def test_end_to_end_physics_informed_bayesopt(ioc, probe, ring):
    """PI-GP BO over CA improves the loss rate in 30 evaluations; the knobs end where they began.

    A plumbing test, not a benchmark: the prior is built from the exact Hessian of the served
    ring's own fast model, and the method is ``pigp-physics`` (the physics form fitted online,
    with that prior's shape; cheap acquisition settings). The IOC's noise is one seeded sequence
    (a value per 50 ms refresh) of which a run reads a stretch that depends on timing (on how
    long the shared IOC has run), so the budget and margin come from repeated runs over CA: the true
    gain of the best-read setting over the start was 0.27-1.14 mA/min after 30 evaluations (10
    runs), 0.03-1.0 after 20 (18 runs) and 0.02-0.9 after 15 (this test's former budget, which
    failed about one run in five); the readings matched their knobs within 3.2 noise sd.
    """
    from pigp_torch.methods import METHODS, RunContext
    from pigp_torch.prior import prior_from_model

    prior = prior_from_model(
        ring.loss_rate, ring.bounds, f_inf=ring.loss_background, noise=NOISE, n_starts=2
    )
    spec = METHODS["pigp-physics"].with_options(n_starts=2)
    x_start = torch.zeros(len(ioc.knob_names), dtype=torch.float64)
    with machine(ioc, ring.bounds) as m:
        optimizer = spec.build(RunContext(machine=m, prior=prior, seed=0))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # GP fitting chatter
            table = optimize(m, optimizer, budget=30)
    X = torch.tensor(table[list(ring.knob_names)].to_numpy(), dtype=torch.float64)
    f_true = ring.loss_rate(X)
    f0 = float(f_true[0])
    assert torch.equal(X[0], x_start)
    best_observed = int(table["y"].idxmax())
    assert float(f_true[best_observed]) > f0 + 2.5 * NOISE, (f0, f_true.tolist())
    assert torch.equal(probe.read_many(ioc.setpoint_pvs), x_start)
    assert torch.equal(probe.read_many(ioc.readback_pvs), x_start)
