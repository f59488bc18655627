"""Tests of Dask sweeps: a loopback LocalCluster reproduces the local table; clear errors."""

import socket
import time

import pandas as pd
import pytest
import torch

pytest.importorskip("distributed")

from distributed import LocalCluster

from pigp_torch.bench import METHODS, run_benchmark
from pigp_torch.bench import distributed as distributed_module
from pigp_torch.bench.distributed import LOCAL_START_TIMEOUT, WORKER_ENV, run_on_dask
from tests.benchmark.conftest import CHEAP_BO, MODEL_SEED, OPTIMUM_STARTS, SEEDS

TIMING = ["ask_time_s", "eval_time_s"]
BUDGETS = {"gp": 6, "direct": 6}


def grid_kwargs(prior):
    return {
        "model_seed": MODEL_SEED,
        "budgets": BUDGETS,
        "archive_size": 40,
        "progress": False,
        "prior": prior,
        "optimum_starts": OPTIMUM_STARTS,
    }


def tiny_grid():
    return [METHODS["nelder-mead"], METHODS["pigp"].with_options(**CHEAP_BO)]


@pytest.fixture(scope="module")
def loopback_cluster():
    """Two single-threaded worker processes on 127.0.0.1, closed when the module's tests end."""
    cluster = LocalCluster(
        n_workers=2,
        threads_per_worker=1,
        processes=True,
        host="127.0.0.1",
        dashboard_address=None,
        env=dict(WORKER_ENV),
        death_timeout=LOCAL_START_TIMEOUT,  # bounded start-up of the worker processes
    )
    try:
        yield cluster
    finally:
        cluster.close()


def free_loopback_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def slow_square(job):
    """A job whose run time decreases with its index, so tasks finish out of job order."""
    i, n = job
    time.sleep(0.1 * (n - i))
    return i * i


@pytest.mark.slow
def test_dask_cluster_gives_the_local_table(loopback_cluster, tiny_prior):
    """methods x seeds on a 2-worker loopback cluster equals the serial run, row for row
    (wall-time columns aside), in method-then-seed order."""
    kwargs = grid_kwargs(tiny_prior)
    address = loopback_cluster.scheduler_address
    assert address.startswith("tcp://127.0.0.1:")
    start = time.perf_counter()
    remote = run_benchmark(tiny_grid(), SEEDS, scheduler=address, **kwargs)
    assert time.perf_counter() - start < 600  # a hang guard: 20 s on an idle 2-core machine
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as on the workers: BLAS threads change the round-off of GP solves
    try:
        local = run_benchmark(tiny_grid(), SEEDS, **kwargs)
    finally:
        torch.set_num_threads(threads)
    assert len(remote) == 2 * len(SEEDS) * BUDGETS["gp"]
    runs = remote[["method", "machine_seed"]].drop_duplicates().to_records(index=False).tolist()
    assert runs == [("nelder-mead", 1), ("nelder-mead", 2), ("pigp", 1), ("pigp", 2)]
    pd.testing.assert_frame_equal(local.drop(columns=TIMING), remote.drop(columns=TIMING))


@pytest.mark.slow
def test_results_come_back_in_job_order(loopback_cluster):
    """Tasks that finish in reverse order are still returned in job order; on_done sees every
    job once, with its label."""
    n = 6
    seen = []
    address = loopback_cluster.scheduler_address
    out = run_on_dask(
        slow_square,
        [(i, n) for i in range(n)],
        scheduler=address,
        labels=[f"square {i}" for i in range(n)],
        on_done=lambda i, label: seen.append((i, label)),
    )
    assert out == [i * i for i in range(n)]
    assert sorted(seen) == [(i, f"square {i}") for i in range(n)]
    same_label = run_on_dask(
        slow_square, [(i, 2) for i in range(2)], scheduler=address, labels=["run", "run"]
    )
    assert same_label == [0, 1]  # one task per job even when labels repeat


@pytest.mark.slow
def test_local_scheduler_starts_and_closes_its_own_cluster(tiny_prior):
    """scheduler="local" runs the grid on its own loopback cluster: same numbers as serial."""
    kwargs = grid_kwargs(tiny_prior)
    grid = [METHODS["nelder-mead"]]
    remote = run_benchmark(grid, SEEDS, scheduler="local", n_workers=2, **kwargs)
    local = run_benchmark(grid, SEEDS, **kwargs)
    pd.testing.assert_frame_equal(local.drop(columns=TIMING), remote.drop(columns=TIMING))


def test_worker_exception_reaches_the_caller(loopback_cluster):
    """An exception raised in a task is re-raised by run_on_dask (not swallowed)."""
    with pytest.raises(ZeroDivisionError):
        run_on_dask(lambda job: 1 / job, [1, 0, 2], scheduler=loopback_cluster.scheduler_address)


def test_unreachable_scheduler_fails_fast_and_clearly():
    """No scheduler on the address: a ConnectionError naming it, within the timeout."""
    address = f"tcp://127.0.0.1:{free_loopback_port()}"
    start = time.perf_counter()
    with pytest.raises(ConnectionError, match=r"could not reach the Dask scheduler at 'tcp://"):
        run_on_dask(abs, [1, -2], scheduler=address, timeout=2.0)
    assert time.perf_counter() - start < 10


def test_benchmark_checks_the_scheduler_before_the_prior(monkeypatch):
    """run_benchmark with an unreachable scheduler fails within the connect timeout, before it
    spends time on the prior (no prior given here)."""
    monkeypatch.setattr(distributed_module, "CONNECT_TIMEOUT", 1.0)
    address = f"tcp://127.0.0.1:{free_loopback_port()}"
    start = time.perf_counter()
    with pytest.raises(ConnectionError, match="could not reach the Dask scheduler"):
        run_benchmark(["pigp"], [1], scheduler=address, progress=False)
    assert time.perf_counter() - start < 5


def test_bad_arguments_raise_value_errors():
    """Empty scheduler, zero workers, mismatched labels are refused before any connection."""
    with pytest.raises(ValueError, match="scheduler must be 'local' or an address"):
        run_on_dask(abs, [1], scheduler="")
    with pytest.raises(ValueError, match="n_workers must be >= 1"):
        run_on_dask(abs, [1], n_workers=0)
    with pytest.raises(ValueError, match="2 labels for 1 jobs"):
        run_on_dask(abs, [1], labels=["a", "b"])
    assert run_on_dask(abs, [], scheduler="tcp://127.0.0.1:1") == []


def test_run_jobs_here_keeps_job_order_serially_and_on_a_process_pool(capsys):
    """run_jobs without a scheduler: the results of fn in job order, serially and on two
    processes alike; with progress, a bar that counts every job."""
    from pigp_torch.bench.distributed import run_jobs

    jobs = [-3, 1, -4, 1, -5]
    assert run_jobs(abs, jobs) == [3, 1, 4, 1, 5]
    assert run_jobs(abs, jobs, n_workers=2) == [3, 1, 4, 1, 5]
    assert run_jobs(abs, jobs, progress=True) == [3, 1, 4, 1, 5]
    assert "5/5" in capsys.readouterr().err
