"""`stereo-bench`: the command line of the calibration benchmark."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

from .config import ConfigError, load_rig

console = Console(stderr=True)


def progress_bar() -> Progress:
    return Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                    TimeRemainingColumn(), console=console, transient=False)


def cmd_render(args) -> int:
    from .dataset import write_dataset

    cfg = load_rig(args.rig)
    out = Path(args.out or Path("out") / cfg.name)
    with progress_bar() as bar:
        task = bar.add_task(f"render {cfg.name}", total=None)
        ds = write_dataset(cfg, out, lambda d, n: bar.update(task, completed=d, total=n))
    for cam, frames in ds.manifest["frames_out_of_view"].items():
        if frames:
            console.print(f"[yellow]{cam}: board partly out of view in {len(frames)} of "
                          f"{ds.frames} frames: {frames}")
    console.print(f"wrote {ds.frames} frames x {len(ds.cameras)} cameras to {out}")
    return 0


def _methods(text: str) -> list[str]:
    from .calibrate import available_methods

    methods = [m.strip() for m in text.split(",") if m.strip()]
    unknown = [m for m in methods if m not in available_methods()]
    if unknown or not methods:
        raise ValueError(f"--methods: unknown {unknown or text!r}; available: "
                         f"{','.join(available_methods())}")
    return methods


def cmd_calibrate(args) -> int:
    import json

    from .dataset import Dataset, write_dataset
    from .evaluate import evaluate_dataset
    from .report import aggregate, markdown

    methods = _methods(args.methods)
    if args.trials < 1:
        raise ValueError(f"--trials: expected at least 1, got {args.trials}")
    base = Dataset.load(args.dataset)
    out = Path(args.out or Path(args.dataset) / "calibration")
    trials = []
    with progress_bar() as bar:
        for i in range(args.trials):
            seed = base.config.seed + i
            tdir = out / "trials" / f"seed_{seed}"
            cached = tdir / "metrics.json"
            if cached.is_file() and json.loads(cached.read_text()).get("methods") == methods:
                trials.append(json.loads(cached.read_text()))
                continue
            if i == 0:
                ds = base
            else:
                ddir = tdir / "dataset"
                try:
                    ds = Dataset.load(ddir)
                except FileNotFoundError:
                    task = bar.add_task(f"render seed {seed}", total=None)
                    cfg = base.config.model_copy(update={"seed": seed})
                    ds = write_dataset(cfg, ddir, lambda d, n: bar.update(task, completed=d,
                                                                         total=n))
            task = bar.add_task(f"detect seed {seed}", total=None)
            trials.append(evaluate_dataset(
                ds, methods, tdir, lambda d, n: bar.update(task, completed=d, total=n)))
    agg = aggregate(trials)
    (out / "metrics.json").write_text(json.dumps({"aggregate": agg, "trials": trials}, indent=2))
    md = markdown(agg, f"{base.config.name}: {base.config.pattern.kind}, "
                       f"{base.config.environment.kind}")
    (out / "metrics.md").write_text(md)
    console.print(md, markup=False, soft_wrap=True, highlight=False)
    console.print(f"wrote {out}/metrics.json, metrics.md and calibrations per trial")
    return 0


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
    c.add_argument("--methods", default="zhang,tsai,bouguet,opencv",
                   help="comma-separated methods (default: %(default)s; also opencv-rational)")
    c.add_argument("--out", help="output directory (default: DATASET/calibration)")
    c.add_argument("--trials", type=int, default=1,
                   help="re-render with N seeds (seed, seed+1, ...) and report mean ± std")
    c.set_defaults(func=cmd_calibrate)
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (ConfigError, FileNotFoundError, ValueError) as e:
        console.print(f"[red]error:[/red] {e}")
        return 2


if __name__ == "__main__":
    sys.exit(main())
