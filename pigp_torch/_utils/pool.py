r"""Independent jobs on a few worker processes, or in this process: :func:`job_pool`.

A job here is a seeded, single-threaded computation (a surrogate network's training, a ring's
optimum, one benchmark run): it gives the same numbers wherever it runs, so spreading jobs over
processes changes only the wall time. On a two-core machine two processes make use of both cores
(a GP step or a small network's update is too small to gain from two threads), and on a machine
that other jobs keep busy, the scheduler gives a command with two processes two shares.

The calling process is one of the workers: ``job_pool(n)`` starts ``n - 1`` more, and the caller
runs its own share of the jobs while they run theirs (a spawned interpreter costs a few seconds of
imports and first-call set-up, so the caller does not sit idle). They start with the ``spawn``
method (a clean interpreter each: no inherited threads or locks) and run torch on one thread.
With ``n = 1`` nothing is spawned: :class:`InlineExecutor` runs each job when it is submitted, so
the order of the output is the serial one.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import pickle
from concurrent.futures import Executor, Future, ProcessPoolExecutor


def default_workers(limit: int = 2) -> int:
    """The processes a command uses by default: the CPUs this process may run on, at most
    ``limit`` (default 2)."""
    try:
        cpus = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not Linux
        cpus = os.cpu_count() or 1
    return max(1, min(int(limit), cpus))


class InlineExecutor(Executor):
    """An executor that runs each job at :meth:`submit`, in this process (the one-worker pool)."""

    def submit(self, fn, /, *args, **kwargs) -> Future:
        future: Future = Future()
        try:
            future.set_result(fn(*args, **kwargs))
        except BaseException as err:  # delivered by future.result(), as a process pool does
            if not isinstance(err, Exception):
                raise
            future.set_exception(err)
        return future


def _one_thread() -> None:
    import torch

    torch.set_num_threads(1)


@contextlib.contextmanager
def one_torch_thread():
    """torch on one intra-op thread inside the block; the caller's thread count is restored.

    For a command whose work is many small tensor operations (a GP step, a batched search on a
    13-knob ring): two OpenMP threads on a busy two-core machine spend their time waiting at
    barriers and multiply the CPU time; one thread gives the same numbers.
    """
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


@contextlib.contextmanager
def job_pool(workers: int):
    """An executor of ``workers - 1`` processes (``spawn``, torch on one thread each; the caller
    is the other worker), or an :class:`InlineExecutor` for ``workers == 1``; shut down (waiting
    for its jobs) on exit.

    Raises:
        ValueError: ``workers < 1``.
    """
    if int(workers) < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    if int(workers) == 1:
        yield InlineExecutor()
        return
    ctx = multiprocessing.get_context("spawn")
    pool = ProcessPoolExecutor(
        max_workers=int(workers) - 1, mp_context=ctx, initializer=_one_thread
    )
    try:
        yield pool
    except BaseException:
        pool.shutdown(wait=False, cancel_futures=True)
        raise
    else:
        pool.shutdown(wait=True)


def _run_pickled(payload: bytes):
    fn, args, kw = pickle.loads(payload)  # our own bytes, from the caller of spread()
    return fn(*args, **kw)


def spread(pool, jobs, local) -> list:
    """Futures of ``jobs`` (``(fn, args, kwargs)`` each, in their order): every job whose index
    is not in ``local`` is submitted to ``pool`` first, then those in ``local`` run here.

    A job for another process is pickled here, before anything runs: a process pool pickles its
    arguments later, on a thread of its own, and torch's multiprocessing pickler moves a
    tensor's storage into shared memory as it goes, which would pull the storage from under a
    job that reads the same tensor here at that moment (a crash in torch's kernels).
    """
    futures: dict = {}
    for i, (fn, args, kw) in enumerate(jobs):
        if i not in local:
            if isinstance(pool, InlineExecutor):
                futures[i] = pool.submit(fn, *args, **kw)
            else:
                futures[i] = pool.submit(_run_pickled, pickle.dumps((fn, args, kw)))
    here = InlineExecutor()
    for i in sorted(local):
        fn, args, kw = jobs[i]
        futures[i] = here.submit(fn, *args, **kw)
    return [futures[i] for i in range(len(jobs))]
