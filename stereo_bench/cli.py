"""`stereo-bench`: the command line of the calibration benchmark."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn
from rich.text import Text

from .config import ConfigError, load_rig, parse_rig
from .rundir import locked

console = Console(stderr=True)
MAX_TRIALS = 1000
MAX_WORKERS = 64


def progress_bar() -> Progress:
    return Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                    TimeRemainingColumn(), console=console, transient=False)


def say(label: str, style: str, message: str) -> None:
    """``label: message`` on stderr; the message is printed as is (no rich markup, so a
    bracket in a file name or a list cannot change it)."""
    console.print(Text(f"{label}: ", style=style) + Text(message), highlight=False,
                  soft_wrap=True)


def _warn(lines) -> None:
    for line in lines:
        say("warning", "yellow", line)


def cmd_render(args) -> int:
    from .dataset import write_dataset

    cfg = load_rig(args.rig)
    out = Path(args.out or Path("out") / cfg.name)
    with locked(out), progress_bar() as bar:
        task = bar.add_task(f"render {cfg.name}", total=None)
        ds = _named(args.rig, write_dataset, cfg, out,
                    lambda d, n: bar.update(task, completed=d, total=n))
    _warn(ds.warnings)
    console.print(f"wrote {ds.frames} frames x {len(ds.cameras)} cameras to {out}")
    return 0


def _named(source, fn, *args):
    """``fn(*args)``, with a refusal of the rig (UnusableRigError) naming ``source``."""
    from .dataset import UnusableRigError

    try:
        return fn(*args)
    except UnusableRigError as e:
        raise ConfigError(f"{source}: {e}") from None


def _methods(text: str) -> list[str]:
    from .calibrate import check_methods

    methods = [m.strip() for m in text.split(",") if m.strip()]
    try:
        # BASE-MODEL variants too; an empty list is refused as the text it came from.
        check_methods(methods or [text])
    except ValueError as e:
        raise ValueError(f"--methods: {e}") from None
    return methods


def _report(trials: list[dict], out: Path, title: str) -> dict:
    from .report import markdown, write_report

    agg = write_report(out, trials, title)
    console.print(markdown(agg, title), markup=False, soft_wrap=True, highlight=False)
    _warn(agg["warnings"] + agg["notes"])
    return agg


def _nothing_calibrated(trials: list[dict]) -> bool:
    return all("error" in entry for t in trials for cams in t["calibration"].values()
               for entry in cams.values())


def _run(cfg, out: Path, args, source, first_dataset=None, with_rig=True) -> list[dict]:
    from .pipeline import run

    methods = _methods(args.methods)
    if not 1 <= args.trials <= MAX_TRIALS or not 1 <= args.workers <= MAX_WORKERS:
        raise ValueError(f"--trials: expected 1..{MAX_TRIALS}; --workers: expected "
                         f"1..{MAX_WORKERS}; got {args.trials} and {args.workers}")
    with progress_bar() as bar:
        task = bar.add_task(f"{cfg.name}: trials", total=args.trials)
        return _named(source, run, cfg, out, methods, args.trials, args.workers,
                      lambda d, n: bar.update(task, completed=d, total=n), first_dataset,
                      with_rig)


def _finish(trials: list[dict], written: str) -> int:
    if _nothing_calibrated(trials):
        say("error", "red", "no camera could be calibrated with any method (see the failures "
                            f"in the report); wrote {written}")
        return 1
    console.print(f"wrote {written}")
    return 0


def cmd_calibrate(args) -> int:
    from .dataset import Dataset
    from .report import run_title

    base = Dataset.load(args.dataset)
    _warn(base.warnings)
    # The dataset holds no calibration settings (they are not rendered data): the option's.
    cfg = parse_rig({**base.config.model_dump(mode="json"),
                     "calibration": {"intrinsics_views": args.intrinsics_views}},
                    f"--intrinsics-views {args.intrinsics_views} for {args.dataset}")
    out = Path(args.out or Path(args.dataset) / "calibration")
    with locked(out):
        trials = _run(cfg, out, args, args.dataset, first_dataset=base.root, with_rig=False)
        _report(trials, out, run_title(base.config))
    return _finish(trials, f"{out}/results.json, report.md; estimates in "
                           f"{out}/trials/*/calibrations")


def cmd_run(args) -> int:
    from .plots import plot_run
    from .report import run_title

    cfg = load_rig(args.rig)
    out = Path(args.out or Path("out") / cfg.name)
    with locked(out):  # the whole command: trials, report and plots come from one run
        trials = _run(cfg, out, args, args.rig)
        agg = _report(trials, out, run_title(cfg))
        plots = plot_run(out, trials, agg)
    return _finish(trials, f"{out}/results.json, {out}/report.md and {len(plots)} plots in "
                           f"{out}/plots")


def cmd_sweep(args) -> int:
    from .sweep import load_grid, run_sweep

    sweep = load_grid(args.grid)
    grid, configs = sweep.grid, sweep.configurations
    out = Path(args.out or Path("out") / grid.name)
    console.print(f"{len(configs)} configurations x {sweep.trials} trial(s) "
                  f"({sweep.trials_reason})", markup=False, highlight=False)
    with progress_bar() as bar:
        task = bar.add_task(f"{grid.name}: configurations", total=len(configs))
        result = run_sweep(sweep, out, args.workers,
                           lambda d, n: bar.update(task, completed=d, total=n))
    stages = result["stage_time_s"]
    console.print(f"{len(configs)} configurations in {result['wall_time_s']:.0f} s wall time "
                  f"with {args.workers} worker(s); summed stage times: "
                  + ", ".join(f"{k[:-2]} {v:.0f} s" for k, v in stages.items())
                  + f"; dominant stage: {max(stages, key=stages.get)[:-2]}")
    if result["failed"]:
        say("warning", "yellow", f"{len(result['failed'])} configuration(s) failed (see "
                                 f"sweep.md): {', '.join(result['failed'])}")
    console.print(f"wrote {out}/sweep.json, {out}/sweep.md and {len(result['curves'])} "
                  f"figure(s) in {out}/curves", markup=False, highlight=False)
    return 0


def _trial_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--methods", default="zhang,tsai,bouguet,opencv",
                   help="comma-separated methods (default: %(default)s; also opencv-rational)")
    p.add_argument("--trials", type=int, default=1,
                   help="re-render with N seeds (seed, seed+1, ...) and report mean ± std")
    p.add_argument("--workers", type=int, default=1,
                   help="trials run in parallel processes (default: %(default)s)")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="stereo-bench",
        description="Benchmark camera calibration patterns and algorithms against exact "
                    "synthetic ground truth.")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    r = sub.add_parser("render", help="render a rig's captures and ground truth to a dataset",
                       description="Render every camera and frame of RIG (YAML) with the "
                                   "analytic renderer; write images, ground truth and a "
                                   "manifest (docs/dataset_format.md).")
    r.add_argument("rig", help="rig YAML file (see configs/)")
    r.add_argument("--out", help="output directory (default: out/<rig name>)")
    r.set_defaults(func=cmd_render)

    c = sub.add_parser("calibrate", help="detect, calibrate with every method, score vs truth",
                       description="Detect the board in DATASET (written by `render`), "
                                   "calibrate every camera with every method, and score each "
                                   "estimate against the ground truth.")
    c.add_argument("dataset", help="dataset directory written by `stereo-bench render`")
    c.add_argument("--out", help="output directory (default: DATASET/calibration)")
    c.add_argument("--intrinsics-views", default="all", choices=["all", "closeups", "session"],
                   help="the views each camera's intrinsics come from (a session dataset: its "
                        "close-ups or its walk; default: %(default)s)")
    _trial_options(c)
    c.set_defaults(func=cmd_calibrate)

    u = sub.add_parser("run", help="the whole benchmark of one rig (also: stereo-bench RIG.yaml)",
                       description="Render -> detect -> calibrate every camera with every "
                                   "method -> calibrate the rig -> triangulate -> metrics -> "
                                   "results.json, report.md and plots. Stages whose outputs "
                                   "are complete are reused.")
    u.add_argument("rig", help="rig YAML file (see configs/)")
    u.add_argument("--out", help="run directory (default: out/<rig name>)")
    _trial_options(u)
    u.set_defaults(func=cmd_run)

    w = sub.add_parser("sweep", help="run a grid of configurations (e.g. the paper's 40)",
                       description="Cross rig files with axes of rig-file fields (GRID.yaml, "
                                   "see docs/sweeps.md and configs/grids/) and run each "
                                   "configuration in parallel processes; one table for the whole "
                                   "grid, curves with 95 % intervals over seeds and paired "
                                   "comparisons of methods and patterns.")
    w.add_argument("grid", help="grid YAML file")
    w.add_argument("--out", help="output directory (default: out/<grid name>)")
    w.add_argument("--workers", type=int, default=2,
                   help="configurations run in parallel (default: %(default)s)")
    w.set_defaults(func=cmd_sweep)
    return p


def main(argv=None) -> int:
    parser = build_parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    # `stereo-bench RIG.yaml ...` is short for `stereo-bench run RIG.yaml ...`.
    if argv and argv[0].endswith((".yaml", ".yml")):
        argv.insert(0, "run")
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except (ConfigError, FileNotFoundError, ValueError) as e:
        say("error", "red", str(e))
        return 2
    except OSError as e:  # a full disk, a permission, a name the file system refuses
        where = f"{e.filename}: " if e.filename else ""
        say("error", "red", f"{where}{e.strerror or e}")
        return 2


if __name__ == "__main__":
    sys.exit(main())
