"""Runs and sweeps started from the web app: one at a time, in a thread of the server.

A job writes only into its own folder under the app's runs folder (RUNS/<name>/, a safe name):
the rig file it was given (rig.yaml, and grid.yaml for a sweep), then everything the command
line writes there (results.json, report.md, report.html, plots, trials). Its state is polled:
``queued`` -> ``running`` (with the stage and frames done) -> ``done`` or ``failed`` (with the
error). The work is the library's own (pipeline.run_trial, sweep.run_sweep), so a web run and
``stereo-bench`` give the same files; numpy and OpenCV release the GIL, so the server answers
while a job computes.
"""

from __future__ import annotations

import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from ..config import RigConfig
from ..rundir import is_safe_name, locked, write_text

METHODS = ["zhang", "tsai", "bouguet", "opencv"]


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

    def view(self) -> dict:
        return {"id": self.id, "name": self.name, "kind": self.kind, "state": self.state,
                "stage": self.stage, "done": self.done, "total": self.total,
                "error": self.error, "seconds": (self.finished or time.time()) - self.started,
                "report": f"/runs/{self.name}/{'sweep' if self.kind == 'sweep' else 'report'}.html"}


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
            busy = [j for j in self._jobs.values() if j.name == name and
                    j.state in ("queued", "running")]
            if busy:
                raise ValueError(f"name: a job is already writing into {name!r}")
            job = Job(len(self._jobs) + 1, name, kind)
            self._jobs[job.id] = job
        return job

    def start_run(self, name: str, cfg: RigConfig, methods=METHODS) -> Job:
        out = self.folder(name)
        job = self._new(name, "run")
        self._pool.submit(self._guard, job, self._run, job, cfg, out, list(methods))
        return job

    def start_sweep(self, name: str, cfg: RigConfig, axes: dict, trials: int,
                    methods=METHODS) -> Job:
        out = self.folder(name)
        job = self._new(name, "sweep")
        self._pool.submit(self._guard, job, self._sweep, job, cfg, out, axes, trials,
                          list(methods))
        return job

    def _guard(self, job: Job, fn, *args) -> None:
        job.state = "running"
        try:
            fn(*args)
            job.state = "done"
        except Exception as e:  # noqa: BLE001 — reported to the page, the server goes on
            job.state, job.error = "failed", f"{type(e).__name__}: {e}"
        finally:
            job.finished = time.time()

    @staticmethod
    def _progress(job: Job, stages):
        """progress(done, total) naming the stage: each time ``done`` starts again (the
        pipeline counts frames once to render them, once to detect them), the next of
        ``stages``."""
        stages = iter(stages)

        def progress(done: int, total: int) -> None:
            if done < job.done or job.total == 0:
                job.stage = next(stages, job.stage)
            job.done, job.total = done, total
        return progress

    def _run(self, job: Job, cfg: RigConfig, out: Path, methods: list[str]) -> None:
        from ..html_report import write_run_html
        from ..pipeline import run_trial
        from ..plots import plot_run
        from ..report import run_title, write_report

        with locked(out):
            write_text(out / "rig.yaml", yaml.safe_dump(cfg.model_dump(mode="json"),
                                                        sort_keys=False))
            job.stage = "starting"
            trial = run_trial(cfg, out, methods,
                              progress=self._progress(job, ["rendering", "detecting"]))
            job.stage = "report"
            agg = write_report(out, [trial], run_title(cfg))
            write_run_html(out, run_title(cfg), [trial], agg, plot_run(out, [trial], agg), cfg)

    def _sweep(self, job: Job, cfg: RigConfig, out: Path, axes: dict, trials: int,
               methods: list[str]) -> None:
        from ..sweep import load_grid, run_sweep

        out.mkdir(parents=True, exist_ok=True)
        write_text(out / "rig.yaml", yaml.safe_dump(cfg.model_dump(mode="json"),
                                                    sort_keys=False))
        write_text(out / "grid.yaml", yaml.safe_dump(
            {"name": job.name, "rigs": ["rig.yaml"], "axes": axes, "methods": methods,
             "trials": trials}, sort_keys=False))
        sweep = load_grid(out / "grid.yaml")
        job.stage = "configurations"
        run_sweep(sweep, out, workers=1, progress=self._progress(job, ["configurations"]))
