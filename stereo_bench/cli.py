"""`stereo-bench`: the command line of the calibration benchmark."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn
from rich.text import Text

from .config.bounds import ConfigError
from .config.schema import load_rig, parse_rig
from .report.html import write_run_html
from .io.rundir import locked, prepare_output
from .render.blender.client import WorkerError
from .render.blender.environment import WorkerUnavailable
from .run.capture_options import board_from_args, camera_folders
from .config.environments import PRESETS
from .tools import TOOLS

console = Console(stderr=True)
MAX_TRIALS = 1000
DEFAULT_METHODS = "zhang,tsai,bouguet,opencv"
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
    from .scene.dataset import write_dataset

    cfg = _renderable(load_rig(args.rig))
    out = Path(args.out or Path("out") / cfg.name)
    with locked(out), progress_bar() as bar:
        task = bar.add_task(f"render {cfg.name}", total=None)
        ds = _named(args.rig, write_dataset, cfg, out,
                    lambda d, n: bar.update(task, completed=d, total=n))
    _warn(ds.warnings)
    console.print(f"wrote {ds.frames} frames x {len(ds.cameras)} cameras to {out}")
    return 0


def _renderable(cfg):
    """``cfg``, once its renderer can run: the Blender backend's worker environment is checked
    before anything is written (WorkerUnavailable says how to build it)."""
    if cfg.renderer.kind == "blender":
        from .render.blender.environment import require

        require()
    return cfg


def _named(source, fn, *args):
    """``fn(*args)``, with a refusal of the rig (UnusableRigError) naming ``source``."""
    from .scene.dataset import UnusableRigError

    try:
        return fn(*args)
    except UnusableRigError as e:
        raise ConfigError(f"{source}: {e}") from None


def _methods(text: str | None, lens: str | None = None) -> list[str]:
    """--methods as a list (None: the default list); with --lens, each made to fit that lens
    model: by default every listed method that can, else each given one or a refusal."""
    from .calibrate import check_methods, methods_for_lens

    methods = [m.strip() for m in (text or DEFAULT_METHODS).split(",") if m.strip()]
    try:
        # BASE-MODEL variants too; an empty list is refused as the text it came from.
        check_methods(methods or [text])
    except ValueError as e:
        raise ValueError(f"--methods: {e}") from None
    if lens is None:
        return methods
    fitting = []
    for m in methods:
        try:
            fitting += methods_for_lens([m], lens)
        except ValueError as e:
            if text is not None:  # a method asked for by name is refused, not dropped
                raise ValueError(f"--lens {lens}: {e}") from None
    if not fitting:
        raise ValueError(f"--lens {lens}: none of {', '.join(methods)} fits it")
    return list(dict.fromkeys(fitting))


def _report(trials: list[dict], out: Path, title: str) -> dict:
    from .report.markdown import markdown, write_report

    agg = write_report(out, trials, title)
    console.print(markdown(agg, title), markup=False, soft_wrap=True, highlight=False)
    _warn(agg["warnings"] + agg["notes"])
    return agg


def _nothing_calibrated(trials: list[dict]) -> bool:
    return all("error" in entry for t in trials for cams in t["calibration"].values()
               for entry in cams.values())


def _workers(args):
    """The command's worker processes (``run.workers.Workers``), started at their first job."""
    from .run.workers import Workers

    if not 1 <= args.trials <= MAX_TRIALS or not 1 <= args.workers <= MAX_WORKERS:
        raise ValueError(f"--trials: expected 1..{MAX_TRIALS}; --workers: expected "
                         f"1..{MAX_WORKERS}; got {args.trials} and {args.workers}")
    return Workers(args.workers)


def _run(cfg, out: Path, args, source, workers, first_dataset=None,
         with_rig=True) -> list[dict]:
    from .run.pipeline import run

    methods = _methods(args.methods)
    with progress_bar() as bar:
        task = bar.add_task(f"{cfg.name}: trials", total=args.trials)
        return _named(source, run, cfg, out, methods, args.trials, workers,
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
    from .scene.dataset import Dataset
    from .report.markdown import run_title

    base = Dataset.load(args.dataset)
    _warn(base.warnings)
    # The dataset holds no calibration settings (they are not rendered data): the option's.
    cfg = parse_rig({**base.config.model_dump(mode="json"),
                     "calibration": {"intrinsics_views": args.intrinsics_views}},
                    f"--intrinsics-views {args.intrinsics_views} for {args.dataset}")
    out = Path(args.out or Path(args.dataset) / "calibration")
    workers = _workers(args)  # a refused option leaves no folder behind
    with locked(out), workers:
        trials = _run(cfg, out, args, args.dataset, workers, first_dataset=base.root,
                      with_rig=False)
        agg = _report(trials, out, run_title(base.config))
        write_run_html(out, run_title(base.config), trials, agg, [], cfg)
    return _finish(trials, f"{out}/results.json, report.md, report.html; estimates in "
                           f"{out}/trials/*/calibrations")


def cmd_run(args) -> int:
    from .report.plots import plot_run
    from .report.markdown import run_title

    cfg = _renderable(load_rig(args.rig))
    out = Path(args.out or Path("out") / cfg.name)
    # The whole command holds the lock (trials, report and plots come from one run) and
    # shares its worker processes between the stages and the plots; a refused option leaves no
    # folder behind.
    workers = _workers(args)
    with locked(out), workers:
        trials = _run(cfg, out, args, args.rig, workers)
        agg = _report(trials, out, run_title(cfg))
        plots = plot_run(out, trials, agg, workers)
        write_run_html(out, run_title(cfg), trials, agg, plots, cfg)
    return _finish(trials, f"{out}/results.json, {out}/report.md, {out}/report.html and "
                           f"{len(plots)} plots in {out}/plots")


#: Processes of a sweep's embedded cluster when --workers is not given.
SWEEP_WORKERS = 2


def _cluster_options(parser, what: str) -> None:
    """--out, --workers and --scheduler of the commands that run on a Dask cluster."""
    parser.add_argument("--out", help=f"output directory (default: out/<{what} name>); with "
                                      f"--scheduler a folder every worker sees at the same path")
    parser.add_argument("--workers", type=int,
                        help=f"processes of the embedded cluster, configurations run in "
                             f"parallel (default: {SWEEP_WORKERS})")
    parser.add_argument("--scheduler", metavar="ADDRESS",
                        help="run on the Dask cluster of this running scheduler "
                             "(tcp://HOST:PORT) instead of an embedded one; its workers run one "
                             "thread each")


def _check_cluster_options(args) -> None:
    if args.scheduler is not None and args.workers is not None:
        raise ValueError("--workers applies to the embedded cluster; with --scheduler the "
                         "cluster's workers run the configurations (start as many as wanted)")


def cmd_sweep(args) -> int:
    from .run.grid import load_grid
    from .run.sweep import run_sweep

    _check_cluster_options(args)
    sweep = load_grid(args.grid)
    grid, configs = sweep.grid, sweep.configurations
    out = Path(args.out or Path("out") / grid.name)
    console.print(f"{len(configs)} configurations x {sweep.trials} trial(s) "
                  f"({sweep.trials_reason})", markup=False, highlight=False)
    with progress_bar() as bar:
        task = bar.add_task(f"{grid.name}: configurations", total=len(configs))
        result = run_sweep(sweep, out, args.workers or SWEEP_WORKERS,
                           lambda d, n: bar.update(task, completed=d, total=n),
                           scheduler=args.scheduler)
    stages = result["stage_time_s"]
    console.print(f"{len(configs)} configurations in {result['wall_time_s']:.0f} s wall time "
                  f"with {result['workers']} worker(s); summed stage times: "
                  + ", ".join(f"{k[:-2]} {v:.0f} s" for k, v in stages.items())
                  + f"; dominant stage: {max(stages, key=stages.get)[:-2]}")
    if result["failed"]:
        say("warning", "yellow", f"{len(result['failed'])} configuration(s) failed (see "
                                 f"sweep.md): {', '.join(result['failed'])}")
    console.print(f"wrote {out}/sweep.json, {out}/sweep.md and {len(result['curves'])} "
                  f"figure(s) in {out}/curves", markup=False, highlight=False)
    return 0


def cmd_study(args) -> int:
    from .run.study import load_study, run_study

    _check_cluster_options(args)
    study = load_study(args.study)
    out = Path(args.out or Path("out") / study.sweep.grid.name)
    console.print(f"{len(study.sweep.configurations)} configurations x {study.sweep.trials} "
                  f"trial(s) ({study.sweep.trials_reason}); pose: "
                  f"{', '.join(study.pose.detectors)} on {', '.join(study.pose.motions)}",
                  markup=False, highlight=False)
    result = run_study(study, out, args.workers or SWEEP_WORKERS, args.scheduler,
                       lambda message: console.print(f"  {message}", markup=False,
                                                     highlight=False))
    console.print(Path(out / "study.md").read_text(), markup=False, soft_wrap=True,
                  highlight=False)
    if result["failed"]:
        say("warning", "yellow", f"{len(result['failed'])} configuration(s) failed to "
                                 f"calibrate: {', '.join(result['failed'])}")
    console.print(f"wrote {out}/study.json, study.md, study.html, study_<studio>.png and the "
                  f"calibrations in {out}/calibration", markup=False, highlight=False)
    return 0


def cmd_calibrate_images(args) -> int:
    from .run.capture import calibrate_capture, with_measured_diameter
    from .config.schema import CalibrationConfig
    from .scene.image_folders import ImageFolders
    import yaml

    from .report.html import provenance, write_html
    from .report.markdown import capture_markdown
    from .io.rundir import CapturePaths
    from .core.files import write_text

    methods = _methods(args.methods, args.lens)
    pattern, diameter_given = board_from_args(args)
    source = ImageFolders.open(camera_folders(args.cameras), pattern, args.frame_stride,
                               args.max_frames, args.timestamps)
    measured = []
    if hasattr(pattern, "diameter_mm") and not diameter_given:
        source, note = with_measured_diameter(source)
        measured.append(note)
        console.print(note, markup=False, highlight=False)
    out = Path(args.out or Path("out") / "capture")
    given = {}
    if args.intrinsics:
        from . import io
        from .run.capture import given_intrinsics

        given = given_intrinsics(io.load(args.intrinsics, args.intrinsics_format), source,
                                 args.intrinsics)
    calibration = CalibrationConfig(refine_intrinsics=args.refine_intrinsics,
                                    fit_board_warp=args.fit_board_warp)
    if not 2 <= args.folds <= 100:
        raise ValueError(f"--folds: expected 2..100, got {args.folds}")
    console.print(f"{len(source.cameras)} camera(s), {source.frames} frames: "
                  + ", ".join(f"{c.name} {c.width}x{c.height}" for c in source.cameras),
                  markup=False, highlight=False)
    with locked(out), progress_bar() as bar:
        task = bar.add_task("detect", total=None)
        results = calibrate_capture(source, methods, out, calibration, args.folds,
                                    progress=lambda d, n: bar.update(task, completed=d, total=n),
                                    notes_in=measured, given=given,
                                    given_from=args.intrinsics or "")
    paths = CapturePaths(out)
    title = f"Calibration of {', '.join(c.name for c in source.cameras)} from their images"
    text = capture_markdown(results, title)
    write_text(paths.report, text)
    write_html(paths.html, title, text, [paths.root / p for p in results["plots"]], provenance(),
               yaml.safe_dump({"cameras": args.cameras, "pattern": results["pattern"],
                               "methods": methods, "folds": args.folds,
                               "calibration": calibration.model_dump(mode="json")},
                              sort_keys=False), methods=methods)
    console.print(text, markup=False, soft_wrap=True, highlight=False)
    _warn(results["warnings"] + results["notes"])
    for line in results.get("recapture", []):
        say("recapture", "cyan", line)
    calibrated = {cam for cams in results["calibration"].values()
                  for cam, e in cams.items() if "error" not in e}
    if not calibrated:
        say("error", "red", f"no camera could be calibrated with any method; wrote {out}")
        return 1
    console.print(f"wrote {paths.results}, {paths.report}, {paths.html}; estimates in "
                  f"{paths.trial.all_calibrations}", markup=False, highlight=False)
    # Everything that could be computed is written; the exit status still says that a camera
    # asked for, or every method's rig, is missing.
    missing = [c.name for c in source.cameras if c.name not in calibrated]
    no_rig = results["rig"] and all("error" in e for e in results["rig"].values())
    if missing or no_rig:
        say("error", "red", (f"camera(s) {', '.join(map(repr, missing))} not calibrated by any "
                             f"method" if missing else "no method gave a rig") + " (notes)")
        return 1
    return 0


def cmd_export(args) -> int:
    from .run.exchange import estimates_of, write_estimates
    from .io.rundir import CapturePaths

    # The source is read before the output folder is made: a wrong path creates nothing.
    estimates, where = estimates_of(args.source, args.method, args.seed)
    out = Path(args.out or CapturePaths(args.source).export(args.format, args.method))
    with locked(out):
        written, refused = write_estimates(estimates, args.format, out)
    if not written:  # every estimate refused: the input, not the run, is at fault
        raise ValueError("; ".join(f"{label}: {why}" if len(refused) > 1 else why
                                   for label, why in refused.items()))
    console.print(f"{args.method}'s estimates of {where} in {args.format} format:",
                  markup=False, highlight=False)
    for path in written:
        console.print(f"  {path}", markup=False, highlight=False)
    for label, why in refused.items():
        console.print(f"warning: {label} not exported: {why}", markup=False, highlight=False)
    return 0


def cmd_twin(args) -> int:
    from .core.files import write_text
    from .report.markdown import twin_markdown
    from .run.twin import read_capture, run_twin

    capture = Path(args.capture)
    out = Path(args.out or capture / "twin")
    read_capture(capture, args.method, args.seeds)  # a wrong capture or option creates nothing
    with locked(out):
        results = run_twin(capture, args.method, args.seeds, out,
                           progress=lambda text: console.print(text, markup=False,
                                                               highlight=False))
        text = twin_markdown(results)
        write_text(out / "report.md", text)
    console.print(text, markup=False, soft_wrap=True, highlight=False)
    console.print(f"wrote {out}/results.json, {out}/report.md", markup=False, highlight=False)
    return 0


def cmd_compare_tools(args) -> int:
    from .core.files import write_json, write_text
    from .io.rundir import RunPaths
    from .report.markdown import compare_markdown
    from .report.html import provenance, write_html
    from .report.plots import plot_compare
    from .run.compare import compare_tools
    from .tools import parse_tools

    cfg = load_rig(args.rig)
    if args.environment:  # any imaging preset on the rig's cameras and session
        from .config.yaml_reader import load_yaml

        cfg = parse_rig({**load_yaml(args.rig, "rig file"),
                         "environment": {"kind": args.environment}}, args.rig)
    cfg = _renderable(cfg)
    names = parse_tools(args.tools)
    if not 1 <= args.seeds <= MAX_TRIALS or not 1 <= args.workers <= MAX_WORKERS:
        raise ValueError(f"--seeds: expected 1..{MAX_TRIALS}; --workers: expected "
                         f"1..{MAX_WORKERS}; got {args.seeds} and {args.workers}")
    out = Path(args.out or Path("out") / f"{cfg.name}_tools")
    paths = RunPaths(out)
    with locked(out):  # the sessions, the tools' files and the report come from one run
        report = _named(args.rig, compare_tools, cfg, out, names, args.seeds, not args.no_pose,
                        args.motion, lambda text: console.print(text, markup=False,
                                                                highlight=False),
                        args.workers)
        write_json(paths.results, report)
        text = compare_markdown(report)
        write_text(paths.report, text)
        figure = plot_compare(report, out / "compare-tools.png")
        write_html(paths.html, f"Calibration tools against the truth: {cfg.name}", text,
                   [figure], provenance(seeds=[s["seed"] for s in report["seeds"]]))
    console.print(text, markup=False, soft_wrap=True, highlight=False)
    console.print(f"wrote {paths.results}, {paths.report}, {paths.html}, {figure}",
                  markup=False, highlight=False)
    return 0


def cmd_score(args) -> int:
    from .scene.dataset import Dataset
    from .run.exchange import score_calibration
    from .report.markdown import imported_markdown
    from .io.rundir import RunPaths
    from .core.files import write_json, write_text

    ds = Dataset.load(args.dataset)
    out = Path(args.out or Path(args.dataset) / "scored")
    with locked(out):
        report = score_calibration(ds, args.calibration, args.format, out)
        text = imported_markdown(report)
        paths = RunPaths(out)
        write_json(paths.results, report)
        write_text(paths.report, text)
    console.print(text, markup=False, soft_wrap=True, highlight=False)
    console.print(f"wrote {paths.results}, {paths.report}", markup=False, highlight=False)
    return 0


def _trial_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--methods", default=DEFAULT_METHODS,
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

    from .scene.image_folders import MAX_VIDEO_FRAMES
    from .io import FORMATS
    from .calibrate.lens_models import LENS_MODELS

    i = sub.add_parser("calibrate-images",
                       help="calibrate your own images (one folder per camera) with every method",
                       description="Detect the board in each camera's images, calibrate every "
                                   "camera with every method and, for two or more cameras, the "
                                   "rig; report what can be known without ground truth "
                                   "(RPE per view, held-out error, uncertainty, agreement "
                                   "between methods, coverage, flagged views). Frames pair "
                                   "across cameras by the last number in the file name.")
    i.add_argument("cameras", nargs="+", metavar="NAME=FOLDER",
                   help="a camera's folder of JPEG/PNG/TIFF images, a quoted glob such as "
                        "left='data/left*.jpg', or a video (synchronised videos pair by frame "
                        "index); a bare folder is named after itself, a bare folder of videos "
                        "is one camera per video")
    i.add_argument("--frame-stride", dest="frame_stride", type=int, default=1,
                   help="videos: take every Nth frame (default: %(default)s, raised so that "
                        "the longest video gives at most --max-frames)")
    i.add_argument("--max-frames", dest="max_frames", type=int, default=MAX_VIDEO_FRAMES,
                   help="videos: at most this many frames from the longest (default: "
                        "%(default)s)")
    i.add_argument("--timestamps", metavar="CSV",
                   help="videos not triggered together: a CSV with a camera column (camera, "
                        "cam_id, cam or port: a name, or the number it ends with) and a time "
                        "column (time, frame_time or timestamp, s), one row per frame; frames "
                        "pair by nearest time")
    i.add_argument("--board", choices=["checkerboard", "charuco", "symmetric_circles",
                                       "asymmetric_circles"], help="the board's kind")
    i.add_argument("--board-file", help="a YAML file with the rig file's pattern section "
                                        "(docs/rig_format.md) instead of the options below")
    i.add_argument("--inner-corners", dest="inner_corners", metavar="CxR",
                   help="checkerboard: inner corners per row x rows, as OpenCV's patternSize "
                        "(9x6 for a board of 10x7 squares)")
    i.add_argument("--squares", metavar="CxR", help="charuco (or checkerboard): squares")
    i.add_argument("--circles", metavar="CxR",
                   help="circle grids: discs per row x rows (OpenCV's patternSize, e.g. 4x11)")
    i.add_argument("--square-mm", dest="square_mm", type=float, help="square side, mm")
    i.add_argument("--marker-mm", dest="marker_mm", type=float, help="charuco: marker side, mm")
    i.add_argument("--dictionary", help="charuco: the cv2.aruco dictionary, e.g. DICT_5X5_100")
    i.add_argument("--legacy", action="store_const", const=True,
                   help="charuco: a board made by OpenCV before 4.6 (with an even number of "
                        "rows its top-left square is white)")
    i.add_argument("--spacing-mm", dest="spacing_mm", type=float,
                   help="circle grids: centre spacing, mm (asymmetric: OpenCV's squareSize, "
                        "the row pitch)")
    i.add_argument("--diameter-mm", dest="diameter_mm", type=float,
                   help="circle grids: disc diameter, mm (default: measured from the images)")
    i.add_argument("--inverted", action="store_true",
                   help="the board is printed white on black (a board not found as given is "
                        "also tried inverted)")
    i.add_argument("--methods",
                   help=f"comma-separated methods (default: {DEFAULT_METHODS}; also BASE-MODEL "
                        f"names such as zhang-brown, and opencv-rational)")
    i.add_argument("--lens", choices=list(LENS_MODELS),
                   help="the lens model every method fits: fisheye (Kannala-Brandt, as "
                        "cv2.fisheye), omnidir (Mei, as cv2.omnidir), doublesphere, or a "
                        "pinhole family (radtan, rational...); each method of --methods becomes "
                        "METHOD-LENS, by default every method that fits it")
    i.add_argument("--folds", type=int, default=5,
                   help="k of the k-fold held-out error (default: %(default)s)")
    i.add_argument("--intrinsics", metavar="FILE",
                   help="a calibration file (any format of `export`) whose cameras, matched by "
                        "name, keep its intrinsics: only their board poses and the rig are "
                        "fitted (e.g. intrinsics calibrated from separate videos)")
    i.add_argument("--intrinsics-format", dest="intrinsics_format", choices=sorted(FORMATS),
                   help="the format of --intrinsics (default: guessed from the file name)")
    i.add_argument("--refine-intrinsics", dest="refine_intrinsics", action="store_true",
                   help="let the rig's bundle adjustment refine each camera's intrinsics")
    i.add_argument("--fit-board-warp", dest="fit_board_warp", action="store_true",
                   help="fit the board's warp (mrcal's two-parabola bow, mm) in each camera's "
                        "calibration, for the methods that can (zhang and its lens models)")
    i.add_argument("--out", help="output directory (default: out/capture)")
    i.set_defaults(func=cmd_calibrate_images)

    e = sub.add_parser("export", help="write a run's or a capture's estimates for another tool",
                       description="Write one method's estimates (the calibrated rig, or each "
                                   "camera when there is no rig) from a run directory or a "
                                   "calibrate-images folder in another tool's format "
                                   "(docs/formats.md).")
    e.add_argument("source", help="a run directory or a calibrate-images output folder")
    e.add_argument("--format", required=True, choices=sorted(FORMATS))
    e.add_argument("--method", default="opencv", help="the method (default: %(default)s)")
    e.add_argument("--seed", type=int, help="a run's trial seed (default: its first)")
    e.add_argument("--out", help="output folder (default: SOURCE/export/FORMAT/METHOD)")
    e.set_defaults(func=cmd_export)

    s = sub.add_parser("score", help="score a calibration made by another tool against a "
                                     "dataset's truth",
                       description="Read a calibration (any format of docs/formats.md) of a "
                                   "rendered dataset's cameras and score it against the truth "
                                   "as the suite scores its own methods: projection difference "
                                   "and parameter errors per camera; for a rig, RMSE_cal "
                                   "through the suite's detections and the rig's errors.")
    s.add_argument("dataset", help="dataset directory written by `stereo-bench render`")
    s.add_argument("calibration", help="a calibration file or folder")
    s.add_argument("--format", choices=sorted(FORMATS),
                   help="its format (default: guessed from the file names)")
    s.add_argument("--out", help="output folder (default: DATASET/scored)")
    s.set_defaults(func=cmd_score)

    k = sub.add_parser("compare-tools", help="grade the calibration tools people run (OpenCV, "
                                             "mrcal, aniposelib, caliscope, pycolmap, multical) "
                                             "against the truth",
                       description="Render the rig's session (one per seed), detect the board "
                                   "once, and let every tool calibrate the same detections as "
                                   "its users run it; each tool's own file is read back and "
                                   "scored as the suite scores its methods (projection "
                                   "difference, RMSE_cal, camera errors, pose-eval's paired "
                                   "MPJPE cost, time), with 95 % intervals over the seeds and "
                                   "the share of seeds inside each tool's reported 1-sigma.")
    k.add_argument("rig", help="rig YAML file (a pair or a studio; any imaging preset)")
    k.add_argument("--tools", help="comma-separated tools (default: all; %s)"
                   % ", ".join(TOOLS))
    k.add_argument("--seeds", type=int, default=1,
                   help="sessions rendered with seeds seed, seed+1, ... (default: %(default)s)")
    k.add_argument("--workers", type=int, default=1,
                   help="seeds run in parallel processes (default: %(default)s)")
    k.add_argument("--environment", choices=sorted(PRESETS),
                   help="render the session under this imaging preset instead of the rig "
                        "file's (docs/imaging.md)")
    k.add_argument("--motion", default="walk_circle",
                   help="pose-eval's body motion for the pose cost (default: %(default)s)")
    k.add_argument("--no-pose", action="store_true", help="skip pose-eval's pose cost")
    k.add_argument("--out", help="output folder (default: out/<rig name>_tools)")
    k.set_defaults(func=cmd_compare_tools)

    t = sub.add_parser("twin", help="render a twin of your capture and say how far its "
                                    "calibration most likely is from the truth",
                       description="From a calibrate-images output: a rig file with the "
                                   "cameras and board poses the method estimated and the "
                                   "imaging measured on your images, rendered with exact "
                                   "truth over several seeds, run through calibrate-images as "
                                   "your capture was; the real and the twin figures side by "
                                   "side and, where they agree, each method's true errors "
                                   "with 95 % intervals.")
    t.add_argument("capture", help="a calibrate-images output folder")
    t.add_argument("--method", default="opencv",
                   help="whose cameras and board poses the twin replays (default: %(default)s)")
    t.add_argument("--seeds", type=int, default=10, help="twins rendered (default: %(default)s)")
    t.add_argument("--out", help="output folder (default: CAPTURE/twin)")
    t.set_defaults(func=cmd_twin)

    w = sub.add_parser("sweep", help="run a grid of configurations (e.g. the paper's 40)",
                       description="Cross rig files with axes of rig-file fields (GRID.yaml, "
                                   "see docs/sweeps.md and configs/grids/) and run each "
                                   "configuration as a task of a Dask cluster (embedded, or a "
                                   "running one with --scheduler); one table for the whole "
                                   "grid, curves with 95 % intervals over seeds and paired "
                                   "comparisons of methods and patterns.")
    w.add_argument("grid", help="grid YAML file")
    _cluster_options(w, "grid")
    w.set_defaults(func=cmd_sweep)

    st = sub.add_parser("study", help="what calibration costs in 3D pose: calibration "
                                      "sessions and pose evaluation in one run, as a curve and "
                                      "a threshold",
                        description="Run a grid of calibration sessions (a sweep's grid file "
                                    "with a pose section, see docs/study.md and "
                                    "configs/studies/), then triangulate bodies' keypoints "
                                    "(synthetic, a fitted BlazePose error model, or BlazePose "
                                    "on Blender renders under the same imaging) through every "
                                    "calibration; writes each calibration's pose cost against "
                                    "its RMSE_cal and the calibration error at which the cost "
                                    "reaches a share of the detector's floor.")
    st.add_argument("study", help="study YAML file")
    _cluster_options(st, "study")
    st.set_defaults(func=cmd_study)

    v = sub.add_parser("serve", help="the local web app: compose, preview, run, compare",
                       description="Start the web app (docs/web.md) on this machine: compose a "
                                   "rig in a form validated like a rig file, preview any "
                                   "camera's frame and the trajectory, run it or sweep it with "
                                   "live progress, open and compare the reports. It writes "
                                   "only into --runs.")
    v.add_argument("--runs", default="out/web", help="folder of the runs it starts and lists "
                                                     "(default: %(default)s)")
    v.add_argument("--host", default="127.0.0.1",
                   help="address to listen on (default: %(default)s, this machine only)")
    v.add_argument("--port", type=int, default=8765, help="port (default: %(default)s)")
    v.set_defaults(func=cmd_serve)

    b = sub.add_parser("blender-setup", help="build the Blender worker environment",
                       description="Create the environment the Blender backend and the 2D pose "
                                   "detector run in (bpy 5.0.1, mediapipe 0.10.21, numpy<2; "
                                   "about 2 GB from PyPI) at $SYNTHCAL_BLENDER_ENV or inside "
                                   "this environment (docs/photoreal.md).")
    b.add_argument("--check", action="store_true",
                   help="only say whether it is built (exit 1 if not)")
    b.set_defaults(func=cmd_blender_setup)
    return p


def cmd_serve(args) -> int:
    from .web.app import serve

    if not 0 < args.port < 65536:
        raise ValueError(f"--port: expected 1..65535, got {args.port}")
    runs = prepare_output(args.runs, "--runs")
    console.print(f"SynthCal at http://{args.host}:{args.port}/ (runs in {runs}); Ctrl-C stops",
                  markup=False, highlight=False)
    serve(runs, args.host, args.port)
    return 0


def cmd_blender_setup(args) -> int:
    from .render.blender import environment

    reason = environment.status()
    if args.check or reason is None:
        console.print(reason or f"the Blender worker environment is ready: "
                                f"{environment.location()}", markup=False)
        return 1 if reason else 0
    environment.build(lambda what: console.print(what, markup=False))
    return 0


def main(argv=None) -> int:
    parser = build_parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    # `stereo-bench RIG.yaml ...` is short for `stereo-bench run RIG.yaml ...`.
    if argv and argv[0].endswith((".yaml", ".yml")):
        argv.insert(0, "run")
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except (ConfigError, FileNotFoundError, ValueError, WorkerUnavailable, WorkerError) as e:
        say("error", "red", str(e))
        return 2
    except OSError as e:  # a full disk, a permission, a name the file system refuses
        where = f"{e.filename}: " if e.filename else ""
        say("error", "red", f"{where}{e.strerror or e}")
        return 2


if __name__ == "__main__":
    sys.exit(main())
