"""Worker processes for trials and sweeps: one way to start them.

Spawned, not forked: forking after OpenCV has started its thread pool can deadlock (TRAPS.md).
And bound to their parent: a run killed by a signal releases its run directory's lock at once,
while a worker left running would go on writing into that directory, under a later run's lock.
On Linux each worker asks the kernel to end it when its parent dies (prctl PR_SET_PDEATHSIG);
elsewhere a worker ends with its task.
"""

from __future__ import annotations

import ctypes
import multiprocessing
import os
import signal
import sys
from concurrent.futures import ProcessPoolExecutor, as_completed, wait

_PR_SET_PDEATHSIG = 1


def _die_with_parent(parent: int) -> None:
    if sys.platform.startswith("linux"):
        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)
    if os.getppid() != parent:  # the parent died before the request was made
        os._exit(1)


def process_pool(workers: int) -> ProcessPoolExecutor:
    """A pool of ``workers`` spawned processes that end when the process that made them does."""
    return ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"),
                               initializer=_die_with_parent, initargs=(os.getpid(),))


class Workers:
    """``count`` spawned processes (``process_pool``), started at the first job that needs them
    and kept until closed, so that the stages of one command share them: a stage starting a
    pool of its own pays the processes' start again (about 1.5 s on 2 cores: each imports
    numpy, OpenCV and the package). With ``count`` <= 1 every job runs in this process."""

    def __init__(self, count: int):
        self.count = count
        self._pool: ProcessPoolExecutor | None = None

    def map(self, fn, jobs: list, progress=None) -> list:
        """``[fn(job) for job in jobs]``, in this process when ``count`` <= 1 or there is one
        job, else in the processes (``fn`` and the jobs must pickle). Results in the jobs'
        order; ``progress(done, total)`` after each. A job's exception is raised once the jobs
        already running have ended; the jobs not yet started are dropped."""
        if self.count <= 1 or len(jobs) <= 1:
            results = []
            for job in jobs:
                results.append(fn(job))
                if progress:
                    progress(len(results), len(jobs))
            return results
        if self._pool is None:
            self._pool = process_pool(self.count)
        results = [None] * len(jobs)
        futures = {self._pool.submit(fn, job): i for i, job in enumerate(jobs)}
        try:
            for done, fut in enumerate(as_completed(futures), 1):
                results[futures[fut]] = fut.result()
                if progress:
                    progress(done, len(jobs))
        except BaseException:
            for fut in futures:
                fut.cancel()
            wait(futures)
            raise
        return results

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None

    def __enter__(self) -> "Workers":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def worker_count(workers: "int | Workers") -> int:
    return workers.count if isinstance(workers, Workers) else workers


def in_processes(fn, jobs: list, workers: "int | Workers", progress=None) -> list:
    """``Workers.map`` on ``workers`` (kept by the caller), or on a pool of that many
    processes made for these jobs alone."""
    if isinstance(workers, Workers):
        return workers.map(fn, jobs, progress)
    with Workers(workers) as pool:
        return pool.map(fn, jobs, progress)
