"""Sweeps on Dask distributed: the embedded LocalCluster gives the old process pool's numbers,
a scheduler and two workers started here on loopback give them too, and a worker killed while
it runs a configuration costs only that configuration's attempt.

Workers are killed from outside, as a crash or the kernel's OOM killer would: a configuration
in flight holds its folder's lock, whose file names the worker process, and has not yet
written results.json; that process gets SIGKILL. No hook in the package is needed.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import dask
import pytest
import yaml

from stereo_bench.run import sweep as sweep_module
from stereo_bench.cli import main
from stereo_bench.run.sweep import _run_config, run_sweep
from stereo_bench.run.grid import load_grid
from stereo_bench.run.workers import process_pool

ROOT = Path(__file__).resolve().parents[2]
NAMES = ["mono_checkerboard_clean_dist.0-0.3", "mono_checkerboard_clean_dist.0-0.5"]


def _grid(folder: Path) -> Path:
    """Two configurations of one camera (quick start's left one), 5 frames, OpenCV only."""
    rig = yaml.safe_load((ROOT / "configs" / "quickstart.yaml").read_text())
    rig["cameras"] = rig["cameras"][:1]
    rig["trajectory"]["frames"] = 5
    (folder / "mono.yaml").write_text(yaml.safe_dump(rig))
    path = folder / "grid.yaml"
    path.write_text(yaml.safe_dump({"name": "g", "rigs": ["mono.yaml"], "methods": ["opencv"],
                                    "axes": {"cameras.*.dist.0": [0.3, 0.5]}}))
    return path


def _numbers(row: dict):
    """A configuration's row without what the clock says (wall and stage times)."""
    if isinstance(row, dict):
        return {k: _numbers(v) for k, v in row.items()
                if k not in ("timing", "wall_time_s", "time s")}
    if isinstance(row, list):
        return [_numbers(v) for v in row]
    return row


def _rows(out: Path) -> dict[str, dict]:
    result = json.loads((out / "sweep.json").read_text())
    return {r["name"]: r for r in result["configurations"]}


@pytest.fixture(scope="module")
def grid(tmp_path_factory) -> Path:
    return _grid(tmp_path_factory.mktemp("grid"))


@pytest.fixture(scope="module")
def reference(grid, tmp_path_factory) -> dict[str, dict]:
    """Per configuration its row as the sweep's former process pool computed it: the same
    task in spawned processes (``workers.process_pool``), rows as they come back."""
    sweep = load_grid(grid)
    out = tmp_path_factory.mktemp("pool")
    jobs = [(c.config.model_dump(mode="json"), str(out / c.name), sweep.grid.methods,
             sweep.trials) for c in sweep.configurations]
    with process_pool(2) as pool:
        rows = {r["name"]: r for r in pool.map(_run_config, jobs)}
    assert sorted(rows) == NAMES and not any("error" in r for r in rows.values())
    return rows


def _same_as_reference(rows: dict, reference: dict, names=NAMES) -> None:
    for name in names:
        assert "error" not in rows[name], rows[name]["error"]
        got, want = _numbers(rows[name]), _numbers(reference[name])
        assert got["aggregate"] == want["aggregate"], name
        assert got["per_trial"] == want["per_trial"], name
        # Numbers that could differ: the calibration's own error against the truth.
        proj = rows[name]["per_trial"][0]["methods"]["opencv"]["projection_difference_mean_px"]
        assert 0 < proj < 1, proj


@pytest.fixture(scope="module")
def loopback_cluster(tmp_path_factory):
    """A scheduler and two single-threaded workers (each under its nanny), started as the
    user would with distributed's command-line programs, on 127.0.0.1, from a folder of their
    own (the sweep must not depend on their working directory); ended at the end."""
    work = tmp_path_factory.mktemp("cluster")
    file = work / "scheduler.json"
    log = open(work / "cluster.log", "wb")
    env = {**os.environ, "DASK_DISTRIBUTED__SCHEDULER__WORKER_SATURATION": "1.0"}
    started = []

    def start(*args):
        started.append(subprocess.Popen([sys.executable, "-m", *args], cwd=work, env=env,
                                        stdout=log, stderr=log, start_new_session=True))

    try:
        start("distributed.cli.dask_scheduler", "--host", "127.0.0.1", "--port", "0",
              "--no-dashboard", "--scheduler-file", str(file))
        deadline = time.monotonic() + 60
        while not (file.exists() and file.read_text().strip()):
            assert time.monotonic() < deadline and started[0].poll() is None, \
                (work / "cluster.log").read_text()
            time.sleep(0.1)
        address = json.loads(file.read_text())["address"]
        assert address.startswith("tcp://127.0.0.1:")
        for _ in range(2):
            start("distributed.cli.dask_worker", address, "--nthreads", "1", "--host",
                  "127.0.0.1", "--no-dashboard", "--memory-limit", "0")
        from distributed import Client

        with Client(address, timeout=60) as client:
            client.wait_for_workers(2, timeout=60)
        yield address
    finally:
        for proc in reversed(started):  # workers first, then the scheduler
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGTERM)
        for proc in started:
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
        log.close()


class InFlightKiller(threading.Thread):
    """Kills, ``times`` times, the worker process that runs one of the configurations of
    ``out`` (the first seen running; again the same one after each kill): running means its
    lock file names a live process other than one killed here, and results.json is absent."""

    def __init__(self, out: Path, times: int = 1):
        super().__init__(daemon=True)
        self.out, self.times = out, times
        self.killed: list[tuple[str, int]] = []
        self.done = threading.Event()

    def _running(self, name: str) -> int | None:
        folder = self.out / name
        try:
            pid = int((folder / ".lock").read_text().strip() or 0)
        except (OSError, ValueError):
            return None
        if not pid or (folder / "results.json").exists() or pid in {p for _, p in self.killed}:
            return None
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return None
        return pid

    def run(self):
        target = None
        while len(self.killed) < self.times and not self.done.is_set():
            for name in [target] if target else NAMES:
                pid = self._running(name)
                if pid:
                    os.kill(pid, signal.SIGKILL)
                    self.killed.append((name, pid))
                    target = name
                    break
            time.sleep(0.005)


def test_embedded_local_cluster_gives_the_process_pools_numbers(grid, reference, tmp_path,
                                                                capsys):
    out = tmp_path / "s"
    assert main(["sweep", str(grid), "--out", str(out), "--workers", "2"]) == 0
    assert "2 configurations in" in capsys.readouterr().err
    result = json.loads((out / "sweep.json").read_text())
    assert result["workers"] == 2 and result["failed"] == []
    _same_as_reference(_rows(out), reference)
    assert (out / NAMES[0] / "results.json").exists() and (out / "sweep.md").exists()


def test_a_scheduler_and_two_workers_on_loopback(grid, reference, loopback_cluster, tmp_path,
                                                  monkeypatch):
    monkeypatch.chdir(tmp_path)  # a relative --out: the workers run elsewhere
    assert main(["sweep", str(grid), "--out", "s", "--scheduler", loopback_cluster]) == 0
    out = tmp_path / "s"
    result = json.loads((out / "sweep.json").read_text())
    assert result["workers"] == 2 and result["failed"] == []
    _same_as_reference(_rows(out), reference)
    # Each configuration ran in a worker process, not here.
    pids = {int((out / n / ".lock").read_text()) for n in NAMES}
    assert os.getpid() not in pids


def test_a_worker_killed_mid_configuration_loses_only_that_attempt(grid, reference,
                                                                   loopback_cluster, tmp_path):
    out = tmp_path / "s"
    killer = InFlightKiller(out)
    killer.start()
    try:
        result = run_sweep(load_grid(grid), out, scheduler=loopback_cluster)
    finally:
        killer.done.set()
        killer.join()
    [(name, pid)] = killer.killed
    with pytest.raises(ProcessLookupError):
        os.kill(pid, 0)
    # The scheduler ran the killed configuration again, in another worker process, and the
    # other configuration's results are those it computed once.
    assert result["failed"] == []
    assert int((out / name / ".lock").read_text()) != pid
    _same_as_reference(_rows(out), reference)


@pytest.mark.slow  # a third sweep: 20-40 s on a busy 2-core machine
def test_a_configuration_whose_workers_keep_dying_is_recorded_as_failed(grid, reference,
                                                                        tmp_path):
    out = tmp_path / "s"
    killer = InFlightKiller(out)
    killer.start()
    # No death allowed: the first one marks the configuration failed (as the default 3 would
    # after 4 deaths), here on the embedded cluster, whose nanny restarts the worker.
    try:
        with dask.config.set({"distributed.scheduler.allowed-failures": 0}):
            result = run_sweep(load_grid(grid), out, workers=2)
    finally:
        killer.done.set()
        killer.join()
    [(name, _)] = killer.killed
    [other] = [n for n in NAMES if n != name]
    assert result["failed"] == [name]
    rows = _rows(out)
    assert rows[name]["error"].startswith("KilledWorker: ") and "died" in rows[name]["error"]
    assert "KilledWorker" in rows[name]["traceback"]
    _same_as_reference(rows, reference, [other])
    assert name in (out / "sweep.md").read_text()


def test_refusals_name_the_option(grid, tmp_path, capsys, monkeypatch):
    from distributed import LocalCluster

    assert main(["sweep", str(grid), "--out", str(tmp_path / "a"), "--workers", "2",
                 "--scheduler", "tcp://127.0.0.1:1"]) == 2
    assert "--workers applies to the embedded cluster" in capsys.readouterr().err
    assert main(["sweep", str(grid), "--out", str(tmp_path / "a"), "--scheduler",
                 "10.0.0.5"]) == 2
    assert "--scheduler: expected a scheduler's address PROTOCOL://HOST:PORT" in \
        capsys.readouterr().err.replace("\n", "")
    monkeypatch.setattr(sweep_module, "SCHEDULER_TIMEOUT_S", 2)
    assert main(["sweep", str(grid), "--out", str(tmp_path / "b"), "--scheduler",
                 "tcp://127.0.0.1:1"]) == 2
    assert "--scheduler: cannot reach a Dask scheduler at 'tcp://127.0.0.1:1'" in \
        capsys.readouterr().err.replace("\n", "")
    # A worker of two threads would run two configurations in one process.
    with LocalCluster(n_workers=1, threads_per_worker=2, processes=False,
                      dashboard_address=None,
                      scheduler_kwargs={"dashboard_address": "127.0.0.1:0"}) as cluster:
        with pytest.raises(ValueError, match=r"run 2 threads; expected 1"):
            run_sweep(load_grid(grid), tmp_path / "c", scheduler=cluster.scheduler_address)
