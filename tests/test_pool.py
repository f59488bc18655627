"""job_pool / spread: jobs run where they are sent, results come back in order, errors surface."""

import os

import pytest
import torch

from pigp_torch._utils.pool import InlineExecutor, default_workers, job_pool, spread


def _where(k: int) -> tuple[int, int, int]:
    return k, os.getpid(), torch.get_num_threads()


def _fails(k: int) -> int:
    raise ValueError(f"job {k} failed")


def test_one_worker_runs_inline_in_order():
    with job_pool(1) as pool:
        assert isinstance(pool, InlineExecutor)
        out = [f.result() for f in spread(pool, [(_where, (k,), {}) for k in range(3)], {1})]
    assert [k for k, _, _ in out] == [0, 1, 2]
    assert {pid for _, pid, _ in out} == {os.getpid()}


def test_two_workers_share_the_jobs_with_the_caller():
    """The jobs in ``local`` run here; the others in one spawned process on one torch thread;
    the results come back in the jobs' order; a failed job raises at its result."""
    with job_pool(2) as pool:
        futures = spread(
            pool, [(_where, (k,), {}) for k in range(4)] + [(_fails, (4,), {})], {0, 3}
        )
        out = [f.result() for f in futures[:4]]
        with pytest.raises(ValueError, match="job 4 failed"):
            futures[4].result()
    assert [k for k, _, _ in out] == [0, 1, 2, 3]
    here = os.getpid()
    assert out[0][1] == here and out[3][1] == here
    assert out[1][1] != here and out[1][1] == out[2][1]  # one spawned process
    assert out[1][2] == 1 and out[2][2] == 1


def test_a_failed_inline_job_raises_at_its_result():
    with job_pool(1) as pool:
        futures = spread(pool, [(_where, (0,), {}), (_fails, (1,), {})], set())
        assert futures[0].result()[0] == 0
        with pytest.raises(ValueError, match="job 1 failed"):
            futures[1].result()


def test_workers_are_checked():
    with pytest.raises(ValueError, match="workers must be >= 1"), job_pool(0):
        pass
    assert 1 <= default_workers() <= 2
    assert default_workers(limit=1) == 1
