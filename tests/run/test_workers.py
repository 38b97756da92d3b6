"""The command's worker processes: kept between stages (the same processes serve every map),
results in the jobs' order, and a failing job ends the map without running the jobs not yet
started."""

import os
import time

import pytest

from stereo_bench.run.workers import Workers, in_processes


def _pid(_):
    time.sleep(0.2)  # long enough that both processes take a job
    return os.getpid()


def _mark_or_fail(args):
    folder, x = args
    if x == 1:
        raise ValueError("job 1 failed")
    time.sleep(0.3)
    (folder / f"{x}.done").touch()
    return x * x


def test_workers_are_kept_between_maps():
    with Workers(2) as workers:
        first = set(in_processes(_pid, list(range(4)), workers))
        second = set(workers.map(_pid, list(range(4))))
    assert len(first) == 2 and first == second and os.getpid() not in first
    assert in_processes(_pid, [0], Workers(2)) == [os.getpid()]  # one job: no process
    assert in_processes(abs, [-3, 2, -1], 1) == [3, 2, 1]


def test_a_failing_job_ends_the_map_and_drops_the_jobs_not_started(tmp_path):
    def done():
        return {int(p.stem) for p in tmp_path.glob("*.done")}

    with Workers(2) as workers:
        with pytest.raises(ValueError, match="job 1 failed"):
            workers.map(_mark_or_fail, [(tmp_path, x) for x in range(12)])
        ran = done()  # the jobs already handed to a process when job 1 failed
        assert 0 in ran and len(ran) < 8  # of the eleven that would succeed
        assert workers.map(_mark_or_fail, [(tmp_path, 2), (tmp_path, 3)]) == [4, 9]
    assert done() == ran | {2, 3}  # the dropped jobs never ran, not even at the close
