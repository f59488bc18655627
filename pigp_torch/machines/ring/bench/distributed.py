r"""Benchmark sweeps on a Dask distributed cluster: one task per (method, machine seed) run.

:func:`run_on_dask` maps the benchmark's per-run function over its jobs on a
:class:`distributed.Client`: either an existing cluster (a scheduler address such as
``tcp://10.0.0.5:8786``, whose workers must have ``pigp_torch`` installed) or ``"local"``, a
:class:`distributed.LocalCluster` of single-threaded worker processes bound to 127.0.0.1 that lives
for the call. :func:`run_jobs` runs the jobs here (serially or on a process pool) or through it;
:func:`~.run_benchmark` uses Dask when given ``scheduler=``::

    df = run_benchmark(["pigp", "ml2"], range(1, 13), scheduler="tcp://10.0.0.5:8786")

Same numbers as a local run. Every run is seeded by its own ``(method, machine seed)``
(:func:`~.run_seed`) and the machine seed, never by a process-global state,
so where it executes does not matter; results are returned in JOB order (not completion order),
so the concatenated table equals the serial one row for row (wall-time columns aside).

Workers run one task at a time with one BLAS/OpenMP thread (``threads_per_worker=1`` and
``OMP_NUM_THREADS = OPENBLAS_NUM_THREADS = MKL_NUM_THREADS = 1`` for a local cluster; the per-run
function also calls ``torch.set_num_threads(1)``): a GP run is many small linear-algebra calls,
which threads slow down rather than speed up, and runs are the unit of parallelism.
"""

from __future__ import annotations

import functools
import logging
import uuid
import warnings
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from typing import Any

#: Seconds to wait for the scheduler to answer and for the first worker to join.
CONNECT_TIMEOUT = 10.0
#: Seconds a local cluster's worker processes may take to start (spawn + imports; slow on a
#: loaded machine).
LOCAL_START_TIMEOUT = 120.0
#: Environment of the worker processes of a local cluster (one thread per worker).
WORKER_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def _start_local_cluster(n_workers: int, timeout: float):
    from distributed import LocalCluster

    try:
        with warnings.catch_warnings():
            # the scheduler's HTTP routes (loopback) move off a busy 8787 and say so: harmless
            warnings.filterwarnings("ignore", message="Port 8787 is already in use")
            return LocalCluster(
                n_workers=int(n_workers),
                threads_per_worker=1,
                processes=True,
                host="127.0.0.1",
                dashboard_address=None,
                silence_logs=logging.ERROR,
                env=dict(WORKER_ENV),
                death_timeout=max(float(timeout), LOCAL_START_TIMEOUT),
            )
    except Exception as exc:  # start-up errors of dask come as many types; re-raise with context
        raise RuntimeError(
            f"could not start a local Dask cluster of {n_workers} worker processes on "
            f"127.0.0.1: {exc}"
        ) from exc


def _connect(address: str, timeout: float):
    """A :class:`distributed.Client` of ``address`` with at least one worker, or ConnectionError."""
    from distributed import Client

    try:
        client = Client(address, timeout=float(timeout), set_as_default=False)
    except (OSError, TimeoutError) as exc:  # distributed raises OSError on connect time-outs
        raise ConnectionError(
            f"could not reach the Dask scheduler at {address!r} within {timeout:g} s ({exc}); "
            "is `dask scheduler` running there and the address right (e.g. "
            "tcp://127.0.0.1:8786)? Use scheduler='local' for a cluster on this machine."
        ) from exc
    try:
        client.wait_for_workers(1, timeout=float(timeout))
    except (OSError, TimeoutError) as exc:
        client.close()
        raise ConnectionError(
            f"the Dask scheduler at {address!r} has no workers after {timeout:g} s: start some "
            f"with `dask worker {address}`"
        ) from exc
    return client


def check_scheduler(scheduler: str, timeout: float | None = None) -> None:
    """Fail early (before expensive set-up) if ``scheduler`` is not ``"local"`` and cannot be
    reached, or has no worker, within ``timeout`` seconds (default :data:`CONNECT_TIMEOUT`).

    Raises:
        ValueError: ``scheduler`` is not a non-empty string.
        ConnectionError: as :func:`run_on_dask`.
    """
    _check_scheduler_text(scheduler)
    if scheduler.strip() != "local":
        _connect(scheduler.strip(), CONNECT_TIMEOUT if timeout is None else float(timeout)).close()


def _check_scheduler_text(scheduler) -> None:
    if not isinstance(scheduler, str) or not scheduler.strip():
        raise ValueError(
            f"scheduler must be 'local' or an address like 'tcp://127.0.0.1:8786', got "
            f"{scheduler!r}"
        )


def run_on_dask(
    fn: Callable[[Any], Any],
    jobs: Sequence[Any],
    *,
    scheduler: str = "local",
    n_workers: int = 2,
    labels: Sequence[str] | None = None,
    on_done: Callable[[int, str], None] | None = None,
    timeout: float | None = None,
) -> list:
    r"""``[fn(job) for job in jobs]`` computed as one Dask task per job, in job order.

    Args:
        fn: a picklable (module-level) function of one job, importable on the workers.
        jobs: the job arguments (picklable); job ``i`` becomes task ``pigp-<i>-<label>-<id>``.
        scheduler: ``"local"``: start a :class:`~distributed.LocalCluster` of ``n_workers``
            processes (one thread each) on 127.0.0.1 for this call and close it afterwards; or
            the address of a running scheduler (``"tcp://host:8786"``), whose workers are used
            as they are.
        n_workers: worker processes of the local cluster (ignored for an address).
        labels: one short text per job for progress and task keys (default ``"job <i>"``).
        on_done: called as ``on_done(i, labels[i])`` when job ``i`` finishes (in completion
            order), e.g. to advance a progress bar.
        timeout: seconds to wait for the scheduler to answer and for a first worker (default
            :data:`CONNECT_TIMEOUT`).

    Returns:
        ``[fn(jobs[0]), fn(jobs[1]), ...]``: the results in job order, whatever the order in
        which the tasks finished.

    Raises:
        ValueError: an empty or non-string ``scheduler``, ``n_workers < 1``, labels of the wrong
            length, ``timeout <= 0``.
        ConnectionError: the scheduler cannot be reached, or has no worker, within ``timeout``.
        Exception: the first exception raised by ``fn`` on a worker (the other tasks are
            cancelled).
    """
    jobs = list(jobs)
    timeout, labels = _checked(scheduler, n_workers, timeout, labels, len(jobs))
    if not jobs:
        return []

    from distributed import as_completed

    cluster = None
    if scheduler.strip() == "local":
        cluster = _start_local_cluster(int(n_workers), float(timeout))
        address = cluster.scheduler_address
        timeout = max(float(timeout), LOCAL_START_TIMEOUT)
    else:
        address = scheduler.strip()
    try:
        client = _connect(address, float(timeout))
        try:
            tag = uuid.uuid4().hex[:8]
            futures = [  # unique keys (a repeated key would be ONE task in Dask)
                client.submit(fn, job, key=f"pigp-{i}-{label.replace(' ', '-')}-{tag}", pure=False)
                for i, (job, label) in enumerate(zip(jobs, labels, strict=True))
            ]
            index = {f.key: i for i, f in enumerate(futures)}
            results: list = [None] * len(jobs)
            try:
                for future in as_completed(futures, loop=client.loop):  # len(futures) items
                    i = index[future.key]
                    results[i] = future.result()  # re-raises a worker's exception here
                    if on_done is not None:
                        on_done(i, labels[i])
            except BaseException:
                client.cancel(futures)
                raise
            return results
        finally:
            client.close()
    finally:
        if cluster is not None:
            cluster.close()


def _checked(scheduler, n_workers, timeout, labels, n_jobs) -> tuple[float, list[str]]:
    """:func:`run_on_dask`'s arguments checked: the timeout (default :data:`CONNECT_TIMEOUT`)
    and the labels (default ``"job <i>"``)."""
    _check_scheduler_text(scheduler)
    timeout = CONNECT_TIMEOUT if timeout is None else timeout
    if int(n_workers) < 1:
        raise ValueError(f"n_workers must be >= 1, got {n_workers}")
    if not float(timeout) > 0:
        raise ValueError(f"timeout must be positive, got {timeout}")
    labels = [f"job {i}" for i in range(n_jobs)] if labels is None else [str(s) for s in labels]
    if len(labels) != n_jobs:
        raise ValueError(f"{len(labels)} labels for {n_jobs} jobs")
    return timeout, labels


def run_jobs(
    fn: Callable[[Any], Any],
    jobs: Sequence[Any],
    *,
    scheduler: str | None = None,
    n_workers: int = 1,
    labels: Sequence[str] | None = None,
    progress: bool = False,
) -> list:
    r"""``[fn(job) for job in jobs]``, in job order, where the benchmark asks for it: here
    serially (``scheduler=None``, ``n_workers=1``), on a ``ProcessPoolExecutor`` of
    ``n_workers`` processes (``scheduler=None``), or on Dask (:func:`run_on_dask`, ``scheduler``
    ``"local"`` or an address). With ``progress`` a tqdm bar over the jobs (``labels``: one text
    per job, shown on Dask as each finishes).
    """
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(jobs), desc="benchmark runs")
    try:
        if scheduler is not None:
            on_done = None if bar is None else functools.partial(_advance, bar)
            return run_on_dask(
                fn, jobs, scheduler=scheduler, n_workers=n_workers, labels=labels, on_done=on_done
            )
        if int(n_workers) == 1:
            results = []
            for job in jobs:
                results.append(fn(job))
                if bar is not None:
                    bar.update(1)
            return results
        with ProcessPoolExecutor(max_workers=int(n_workers)) as pool:
            results = []
            for result in pool.map(fn, jobs):  # results in job order
                results.append(result)
                if bar is not None:
                    bar.update(1)
            return results
    finally:
        if bar is not None:
            bar.close()


def _advance(bar, _: int, label: str) -> None:
    bar.set_postfix_str(f"finished {label}", refresh=False)
    bar.update(1)
