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
