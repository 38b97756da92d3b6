"""Runs and sweeps started from the web app: one at a time, each in a process of its own.

A job writes only into its own folder under the app's runs folder (RUNS/<name>/, a safe name):
the rig file it was given (rig.yaml, and grid.yaml for a sweep), then everything the command
line writes there (results.json, report.md, report.html, plots, trials). Its state is polled:
``queued`` -> ``running`` (with the stage and frames done) -> ``done``, ``failed`` (with the
error) or ``cancelled``. The work is the library's own (pipeline.run_trial, sweep.run_sweep), so
a web run and ``stereo-bench`` give the same files.

The job runs in a spawned process that leads its own process group (a sweep's Dask workers are
in it too), so that cancelling it is a signal to the group, not a request that a busy loop would
have to notice: the job stops within a second, its lock is released with it, and what it had
finished stays on disk (a rerun reuses it by fingerprint).
"""

from __future__ import annotations

import multiprocessing
import os
import shutil
import signal
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

from ..config.schema import RigConfig
from ..core.files import is_safe_name

METHODS = ["zhang", "tsai", "bouguet", "opencv"]
STOP_SECONDS = 5.0  # from SIGTERM to SIGKILL for a cancelled job's process group


@dataclass
class Job:
    id: int
    name: str
    kind: str  # "run" or "sweep"
    state: str = "queued"
    stage: str = ""
    done: int = 0
    total: int = 0
    error: str | None = None
    started: float = field(default_factory=time.time)
    finished: float | None = None
    cancel: threading.Event = field(default_factory=threading.Event, repr=False)

    def view(self) -> dict:
        return {"id": self.id, "name": self.name, "kind": self.kind, "state": self.state,
                "stage": self.stage, "done": self.done, "total": self.total,
                "error": self.error, "seconds": (self.finished or time.time()) - self.started,
                "report": f"/runs/{self.name}/{'sweep' if self.kind == 'sweep' else 'report'}.html"}

    @property
    def active(self) -> bool:
        return self.state in ("queued", "running")


class Jobs:
    def __init__(self, runs: Path):
        self.runs = Path(runs)
        self._jobs: dict[int, Job] = {}
        self._lock = threading.Lock()
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="job")

    def folder(self, name: str) -> Path:
        """RUNS/<name>, refusing a name that is not a safe folder name (so nothing a request
        says can reach outside the runs folder)."""
        if not isinstance(name, str) or not is_safe_name(name):
            raise ValueError(f"name: expected letters, digits, _ - . (at most 64), got {name!r}")
        return self.runs / name

    def get(self, job_id: int) -> Job | None:
        return self._jobs.get(job_id)

    def all(self) -> list[Job]:
        return list(self._jobs.values())

    def _new(self, name: str, kind: str) -> Job:
        with self._lock:
            if any(j.name == name and j.active for j in self._jobs.values()):
                raise ValueError(f"name: a job is already writing into {name!r}")
            job = Job(len(self._jobs) + 1, name, kind)
            self._jobs[job.id] = job
        return job

    def start_run(self, name: str, cfg: RigConfig, methods=METHODS) -> Job:
        out = self.folder(name)
        job = self._new(name, "run")
        self._pool.submit(self._guard, job, ("run", cfg.model_dump(mode="json"), str(out),
                                             list(methods)))
        return job

    def start_sweep(self, name: str, cfg: RigConfig, axes: dict, trials: int,
                    methods=METHODS) -> Job:
        out = self.folder(name)
        job = self._new(name, "sweep")
        self._pool.submit(self._guard, job, ("sweep", cfg.model_dump(mode="json"), str(out),
                                             list(methods), axes, trials))
        return job

    def cancel(self, job_id: int) -> Job | None:
        """Stop a job: a queued one never starts, a running one's processes are signalled."""
        job = self.get(job_id)
        if job is not None and job.active:
            job.cancel.set()
        return job

    def delete(self, name: str) -> bool:
        """Remove RUNS/<name> (a symlink there is removed, never followed); False when there
        is nothing of that name. Refused while a job writes into it."""
        folder = self.folder(name)
        with self._lock:
            if any(j.name == name and j.active for j in self._jobs.values()):
                raise ValueError(f"name: a job is writing into {name!r}; cancel it first")
            if folder.is_symlink() or folder.is_file():
                folder.unlink()
            elif folder.is_dir():
                shutil.rmtree(folder)
            else:
                return False
        return True

    def _guard(self, job: Job, task: tuple) -> None:
        if job.cancel.is_set():
            job.state, job.finished = "cancelled", time.time()
            return
        job.state = "running"
        ctx = multiprocessing.get_context("spawn")  # a fork would copy OpenCV's thread pool
        ours, theirs = ctx.Pipe(duplex=False)
        proc = ctx.Process(target=_work, args=(task, theirs), daemon=False)
        try:
            proc.start()
            theirs.close()
            outcome = None
            while proc.is_alive() or ours.poll():
                if job.cancel.is_set():
                    _stop(proc)
                    outcome = ("cancelled", None)
                    break
                if not ours.poll(0.2):
                    continue
                try:
                    message = ours.recv()
                except EOFError:
                    break
                if message[0] == "progress":
                    job.stage, job.done, job.total = message[1:]
                else:
                    outcome = message
            proc.join()
            if outcome is None:
                outcome = ("failed", f"the job's process ended with exit code {proc.exitcode}")
            job.state, job.error = outcome
        except Exception as e:  # noqa: BLE001 — reported to the page, the server goes on
            job.state, job.error = "failed", f"{type(e).__name__}: {e}"
        finally:
            ours.close()
            job.finished = time.time()


def _stop(proc) -> None:
    """SIGTERM to the job's process group, SIGKILL after STOP_SECONDS."""
    for sig, wait in ((signal.SIGTERM, STOP_SECONDS), (signal.SIGKILL, None)):
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:  # still starting, not yet leading its group: it alone
            try:
                os.kill(proc.pid, sig)
            except ProcessLookupError:
                return
        proc.join(wait)
        if not proc.is_alive():
            return


def _work(task: tuple, conn) -> None:
    """The job's process: leads a process group of its own, reports progress and the outcome
    on ``conn``."""
    os.setpgrp()
    stages: list[str] = []
    last = {"done": 0, "total": 0, "stage": ""}

    def progress(done: int, total: int) -> None:
        # Each time ``done`` starts again (the pipeline counts frames once to render them, once
        # to detect them), the next stage.
        if done < last["done"] or last["total"] == 0:
            last["stage"] = stages.pop(0) if stages else last["stage"]
        last.update(done=done, total=total)
        conn.send(("progress", last["stage"], done, total))

    try:
        kind, config, out, methods, *rest = task
        from ..config.schema import parse_rig

        cfg = parse_rig(config, "the job's rig")
        if kind == "run":
            stages += ["rendering", "detecting"]
            _run(cfg, Path(out), methods, progress, conn)
        else:
            stages.append("configurations")
            _sweep(cfg, Path(out), methods, *rest, progress)
        conn.send(("done", None))
    except Exception as e:  # noqa: BLE001 — the page says why
        conn.send(("failed", f"{type(e).__name__}: {e}"))
    finally:
        conn.close()


def _rig_yaml(cfg: RigConfig) -> str:
    import yaml

    return yaml.safe_dump(cfg.model_dump(mode="json"), sort_keys=False)


def _run(cfg: RigConfig, out: Path, methods: list[str], progress, conn) -> None:
    from ..report.html import write_run_html
    from ..run.pipeline import run_trial
    from ..report.plots import plot_run
    from ..report.markdown import run_title, write_report
    from ..io.rundir import locked
    from ..core.files import write_text

    with locked(out):
        write_text(out / "rig.yaml", _rig_yaml(cfg))
        conn.send(("progress", "starting", 0, 0))
        trial = run_trial(cfg, out, methods, progress=progress)
        conn.send(("progress", "report", 0, 0))
        agg = write_report(out, [trial], run_title(cfg))
        write_run_html(out, run_title(cfg), [trial], agg, plot_run(out, [trial], agg), cfg)


def grid_data(name: str, axes: dict, trials: int, methods=METHODS) -> dict:
    """The grid file a web sweep writes beside its rig.yaml."""
    return {"name": name, "rigs": ["rig.yaml"], "axes": axes, "methods": list(methods),
            "trials": trials}


def _sweep(cfg: RigConfig, out: Path, methods: list[str], axes: dict, trials: int,
           progress) -> None:
    import yaml

    from ..core.files import write_text
    from ..run.grid import load_grid
    from ..run.sweep import run_sweep

    out.mkdir(parents=True, exist_ok=True)
    write_text(out / "rig.yaml", _rig_yaml(cfg))
    write_text(out / "grid.yaml", yaml.safe_dump(grid_data(out.name, axes, trials, methods),
                                                 sort_keys=False))
    run_sweep(load_grid(out / "grid.yaml"), out, workers=1, progress=progress)
