"""`stereo-bench sweep GRID.yaml`: many rig configurations (e.g. the paper's 40), in parallel,
with curves against any rig-file field and paired comparisons of methods and patterns.

A grid file crosses rig files with axes (docs/sweeps.md is the user's description)::

    name: noise_level
    rigs: [../quickstart.yaml]                # relative to the grid file
    patterns: [checkerboard, charuco]         # shorthand for the axis pattern.kind
    environments: [noisy]                     # shorthand for the axis environment.kind
    axes:                                     # dotted rig-file field path -> values
      trajectory.tilt_deg: [10, 30, 50]
      cameras.*.dist.0: [0.1, 0.5]            # '*': every camera; an integer: one list entry
    methods: [zhang, opencv]
    trials: 4          # seeds per configuration (default: 10 if any is noisy, else 1)
    frames: 20         # optional: shorthand for a one-valued axis trajectory.frames

Every value is set into the rig's resolved configuration (``load_rig(...).model_dump()``) and
the result validated as a rig file, so a path that is no field of the rig, or a value the
field refuses, is refused before anything runs, naming the grid file, the axis and the value.
Axes are crossed with each other and with the rig files. A section's ``kind`` is set first: a
new ``pattern.kind`` drops the base rig's other pattern fields (they describe its board), and a
new ``environment.kind`` starts the environment again from what the rig file itself writes
there, so that the preset of the new kind fills the rest.

Each configuration runs the whole pipeline into OUT/<name>/ as one task of a Dask distributed
cluster (an embedded ``LocalCluster`` of spawned single-threaded processes by default, or a
running scheduler's workers that see OUT at the same path), where <name> is
``<rig>_<pattern>_<environment>`` followed by ``_<field>-<value>`` for every other axis of two
or more values; one that fails is recorded with its error and the others go on, and one whose
worker dies is run again on another worker (up to the scheduler's
``distributed.scheduler.allowed-failures`` deaths, then recorded as failed).
OUT/sweep.json and OUT/sweep.md hold the grid's table, the time per stage, the curves and the
paired comparisons (``sweep_stats``); OUT/curves/*.png the curves' figures.
"""

from __future__ import annotations

import logging
import re
import time
import traceback
import uuid
from contextlib import contextmanager
from pathlib import Path

import cv2

from ..config.schema import RigConfig
from ..report.html import provenance, write_html, write_run_html
from ..report.markdown import fmt, run_title, write_report
from ..io.rundir import locked
from ..core.files import write_json, write_text
from .grid import Sweep

#: Seconds to reach a --scheduler, and to wait for its first worker to join.
SCHEDULER_TIMEOUT_S = 30


def _run_config(args) -> dict:
    from .pipeline import run
    from ..report.plots import plot_run
    from .sweep_stats import trial_values

    cfg_json, out, methods, trials = args
    cfg = RigConfig.model_validate(cfg_json)
    # One configuration per worker thread: OpenCV's own pool would put as many threads as
    # cores in every worker (its BLAS is held to one by the nanny's environment).
    cv2.setNumThreads(1)
    _keep_freed_memory()
    t0 = time.perf_counter()
    try:
        with locked(out):
            results = run(cfg, Path(out), methods, trials)
            agg = write_report(Path(out), results, run_title(cfg))
            write_run_html(Path(out), run_title(cfg), results, agg,
                           plot_run(Path(out), results, agg), cfg)
        return {"name": cfg.name, "aggregate": agg,
                "per_trial": [trial_values(t) for t in results],
                "wall_time_s": time.perf_counter() - t0}
    except Exception as e:  # noqa: BLE001 — one configuration must not end the sweep
        return {"name": cfg.name, "error": f"{type(e).__name__}: {e}",
                "traceback": traceback.format_exc(), "wall_time_s": time.perf_counter() - t0}


def _keep_freed_memory() -> None:
    """Let this worker's C allocator keep the memory a frame frees for the next frame.

    Dask's nanny starts workers with MALLOC_TRIM_THRESHOLD_=65536, which also turns off glibc's
    growing mmap threshold: every array over 128 kB (a 12 MP frame's many) is then mapped and
    unmapped, and its pages zeroed by the kernel, at each frame. Measured on 32 frames of the
    12 MP camera under ``noisy`` with that variable set: 19.5 s wall and 6.5 s system time,
    against 15.0 s and 1.9 s with the thresholds set here. They are
    what glibc would have grown to (its mmap ceiling, 32 MiB on 64-bit) and a trim threshold
    that keeps a frame's working set."""
    import ctypes

    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:  # not glibc: nothing to undo
        return
    m_trim_threshold, m_mmap_threshold = -1, -3
    libc.mallopt(m_mmap_threshold, 32 << 20)
    libc.mallopt(m_trim_threshold, 256 << 20)


def _pixels(cfg: RigConfig) -> int:
    """Pixels a configuration renders and searches: the scheduler starts the largest first
    (a Dask priority), so that the sweep does not end on one large configuration running alone
    while the other workers idle (the paper's grid mixes 12 MP pairs with 0.3 MP monos)."""
    return cfg.trajectory.frames * sum(c.width * c.height for c in cfg.cameras)


@contextmanager
def _dask_client(workers: int, scheduler: str | None):
    """A ``distributed.Client`` on the running scheduler at ``scheduler`` ("tcp://HOST:PORT"),
    or on an embedded ``LocalCluster`` of ``workers`` processes closed on exit; yields the
    client and the number of workers, each checked to run one thread.

    The embedded cluster keeps what the sweep's own process pool did: spawned processes
    (forking after OpenCV has started its thread pool can deadlock, TRAPS.md) that end when
    this process does (each worker exits when its parent's pipe closes), one configuration at
    a time each, no memory limit, and nothing listening beyond loopback."""
    import dask
    from distributed import Client, LocalCluster
    from distributed import TimeoutError as DaskTimeoutError

    if scheduler is None:
        with dask.config.set({"distributed.worker.multiprocessing-method": "spawn",
                              # One task per worker thread: a worker that dies then takes only
                              # the configuration it runs with it (1.1 sends a second one).
                              "distributed.scheduler.worker-saturation": 1.0}):
            # No dashboard; the scheduler's HTTP server (health, metrics) on a free port
            # rather than 8787, which another sweep may hold. Errors only in the terminal:
            # the progress bar speaks for the cluster (a lost configuration is in sweep.md).
            cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                   host="127.0.0.1", dashboard_address=None, memory_limit=0,
                                   scheduler_kwargs={"dashboard_address": "127.0.0.1:0"},
                                   silence_logs=logging.ERROR)
        with cluster, Client(cluster) as client:
            yield client, workers
        return
    if not re.fullmatch(r"[a-z]+://\S+", scheduler):  # distributed asserts on a bare HOST:PORT
        raise ValueError(f"--scheduler: expected a scheduler's address PROTOCOL://HOST:PORT "
                         f"such as tcp://10.0.0.5:8786, got {scheduler!r}")
    try:
        client = Client(scheduler, timeout=SCHEDULER_TIMEOUT_S)
    except (OSError, ValueError) as e:
        raise ValueError(f"--scheduler: cannot reach a Dask scheduler at {scheduler!r} ({e}); "
                         f"expected the address a running `dask scheduler` prints, e.g. "
                         f"tcp://10.0.0.5:8786") from None
    with client:
        try:
            client.wait_for_workers(1, timeout=SCHEDULER_TIMEOUT_S)
        except (TimeoutError, DaskTimeoutError):
            raise ValueError(f"--scheduler {scheduler}: no worker joined within "
                             f"{SCHEDULER_TIMEOUT_S} s; start workers with `dask worker "
                             f"{scheduler} --nthreads 1`") from None
        threads = client.nthreads()
        # pyplot's figures, OpenCV's thread count and the BLAS limits are per process: two
        # configurations in threads of one worker would share them.
        many = sorted(a for a, n in threads.items() if n != 1)
        if many:
            raise ValueError(f"--scheduler {scheduler}: worker(s) {', '.join(many)} run "
                             f"{threads[many[0]]} threads; expected 1 (start them with "
                             f"`dask worker {scheduler} --nthreads 1`, several with "
                             f"--nworkers)")
        yield client, len(threads)


def _gathered(futures: dict, progress=None) -> dict:
    """Per configuration name its row, as each future finishes; a future that raised (its
    workers kept dying: KilledWorker, or the cluster was lost) gives a failed row naming why,
    and the others go on."""
    from distributed import as_completed

    rows = {}
    for n, fut in enumerate(as_completed(futures), 1):
        name = futures[fut]
        try:
            rows[name] = fut.result()
        except Exception as e:  # noqa: BLE001 — a lost configuration must not end the sweep
            rows[name] = {"name": name, "error": f"{type(e).__name__}: {e}",
                          "traceback": "".join(traceback.format_exception(e)),
                          "wall_time_s": None}
        if progress:
            progress(n, len(futures))
    return rows


def run_sweep(sweep: Sweep, out: Path, workers: int = 1, progress=None,
              scheduler: str | None = None) -> dict:
    """Every configuration into OUT/<name>/ (each holding its own run directory's lock), with
    the sweep's lock on OUT held here; sweep.json, sweep.md and curves/*.png last, from here.

    ``scheduler``: the address of a running Dask scheduler whose workers (one thread each)
    see OUT at the same path and have this package installed; None: an embedded LocalCluster
    of ``workers`` processes (``workers`` is not used with a scheduler). ``progress(done,
    total)`` is called per finished configuration."""
    from ..report.plots import plot_sweep_curve
    from .sweep_stats import comparisons, curves, stats_markdown

    if scheduler is None and not 1 <= workers <= 64:
        raise ValueError(f"--workers: expected 1..64, got {workers}")
    grid, configs = sweep.grid, sweep.configurations
    with locked(out) as out:
        # Absolute: a worker elsewhere does not share this process's working directory.
        out = out.resolve()
        jobs = [(c.config.model_dump(mode="json"), str(out / c.name), grid.methods,
                 sweep.trials) for c in configs]
        t0 = time.perf_counter()
        with _dask_client(workers, scheduler) as (client, n_workers):
            # Keys unique per sweep: a key is otherwise a hash of the task's arguments, and a
            # scheduler that still holds an earlier sweep's result under it would return that
            # result instead of running the configuration into this sweep's folders.
            run_id = uuid.uuid4().hex[:8]
            # Submitted largest first too: the first ones start as they arrive.
            order = sorted(range(len(configs)), key=lambda i: -_pixels(configs[i].config))
            futures = {client.submit(_run_config, jobs[i], key=f"sweep-{configs[i].name}-"
                                     f"{run_id}", priority=_pixels(configs[i].config)):
                       configs[i].name for i in order}
            rows = _gathered(futures, progress)
            result = {"name": grid.name, "grid_file": sweep.source, "workers": n_workers,
                      "wall_time_s": time.perf_counter() - t0, "methods": grid.methods,
                      "trials_per_configuration": sweep.trials,
                      "trials_reason": sweep.trials_reason,
                      "axes": [a.to_dict() for a in sweep.axes],
                      "configurations": [{**c.to_dict(), **rows[c.name]} for c in configs]}
            result["failed"] = [r["name"] for r in result["configurations"] if "error" in r]
            result["stage_time_s"] = {
                stage: sum(r["aggregate"]["timing"][stage]["mean"] * r["aggregate"]["trials"]
                           for r in result["configurations"] if "aggregate" in r
                           and r["aggregate"]["timing"][stage]["n"])
                for stage in ("render_s", "detect_s", "calibrate_s", "rig_s")}
            result["curves"] = curves(result)
            result["comparisons"] = comparisons(result)
            # The curves' figures on the workers, idle by now and with matplotlib loaded: the
            # paper's grid has 15, 9 s one after another in this process.
            paths = [out / curve["figure"] for curve in result["curves"]]
            try:
                client.gather(client.map(
                    plot_sweep_curve, result["curves"], paths,
                    key=[f"sweep-curve-{k}-{run_id}" for k in range(len(paths))]))
                drawn = True
            except Exception:  # noqa: BLE001 — a lost cluster must not cost the sweep's tables
                drawn = False
        if not drawn:
            for curve, path in zip(result["curves"], paths):
                plot_sweep_curve(curve, path)
        write_json(out / "sweep.json", result)
        text = sweep_markdown(result) + stats_markdown(result)
        write_text(out / "sweep.md", text)
        write_html(out / "sweep.html", result["name"], text,
                   [out / curve["figure"] for curve in result["curves"]], provenance(),
                   Path(result["grid_file"]).read_text() if Path(result["grid_file"]).is_file()
                   else None, methods=result["methods"])
    return result


def sweep_markdown(result: dict) -> str:
    """The grid's table: per configuration and method the per-camera and rig figures."""
    methods = result["methods"]
    cols = [("RPE_RMS px", "calibration"), ("proj. diff mean px", "calibration"),
            ("RMSE_cal mm", "rig")]
    lines = [f"# {result['name']}", "",
             f"{len(result['configurations'])} configurations, "
             f"{result['trials_per_configuration']} trial(s) each "
             f"({result['trials_reason']}); wall time {result['wall_time_s']:.0f} s with "
             f"{result['workers']} worker(s); summed stage times (s): "
             + ", ".join(f"{k[:-2]} {v:.0f}" for k, v in result["stage_time_s"].items()), "",
             "Per camera for mono columns (camera: value); mean ± std over trials.", "",
             "| configuration | method | " + " | ".join(c for c, _ in cols) + " |",
             "|---|---|" + "---|" * len(cols)]
    for row in result["configurations"]:
        if "error" in row:
            lines.append(f"| {row['name']} | all | failed: {row['error']} |")
            continue
        agg = row["aggregate"]
        for m in methods:
            cells = []
            for col, section in cols:
                if section == "rig":
                    cells.append(fmt(agg["rig"][m][col]) if "rig" in agg else "")
                else:
                    cells.append("; ".join(f"{cam}: {fmt(r[col])}"
                                           for cam, r in agg["calibration"][m].items()))
            lines.append(f"| {row['name']} | {m} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"
