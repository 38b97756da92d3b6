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
from concurrent.futures import ProcessPoolExecutor, as_completed

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


def in_processes(fn, jobs: list, workers: int, progress=None) -> list:
    """``[fn(job) for job in jobs]``, in this process when ``workers`` <= 1 or there is one
    job, else in a pool of ``workers`` spawned processes (``process_pool``; ``fn`` and the jobs
    must pickle). Results in the jobs' order; ``progress(done, total)`` after each."""
    if workers <= 1 or len(jobs) <= 1:
        results = []
        for job in jobs:
            results.append(fn(job))
            if progress:
                progress(len(results), len(jobs))
        return results
    results = [None] * len(jobs)
    with process_pool(workers) as pool:
        futures = {pool.submit(fn, job): i for i, job in enumerate(jobs)}
        for done, fut in enumerate(as_completed(futures), 1):
            results[futures[fut]] = fut.result()
            if progress:
                progress(done, len(jobs))
    return results
