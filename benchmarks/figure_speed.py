"""Time a run's figures (report.plots.plot_run: each kind, each camera) beside the stages of
the same run, on one core.

A sweep draws each configuration's figures on the worker that ran its stages, after them: on
the paper's grid they are about a sixth of the configurations' time. The run is RUN_DIR (a
run's output folder), or by default the paper's wide pair (configs/paper/wide_pair.yaml, 127
frames) run first into a temporary folder. Every figure is drawn ``--repeat`` times in turn;
the table gives the best CPU time of each (this machine's wall times move by 15 % from one
minute to the next) beside the run's stage times as the run measured them.

With ``--baseline REV`` git revision REV draws the same figures into its own copy of the run
(a subprocess on a worktree of REV: revision.py), figure by figure in turn with the working
tree's; the table says how far each image is from REV's (size, and the share of pixels that
differ).

    python benchmarks/figure_speed.py [RUN_DIR] [--repeat 5] [--baseline REV]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"  # before numpy is imported

import argparse  # noqa: E402
import json  # noqa: E402
import shutil  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from contextlib import nullcontext  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from revision import revision_server  # noqa: E402

WIDE_PAIR = Path(__file__).resolve().parent.parent / "configs" / "paper" / "wide_pair.yaml"

# The revision's side: plot_run's one-figure job, whose arguments every revision since the
# figures were drawn in parallel takes alike.
SERVER = """
import time
import cv2
from revision import serve
from stereo_bench.report import plots
cv2.setNumThreads(1)


def answer(job):
    start = time.process_time()
    plots._plot_job(job)
    return time.process_time() - start


serve(answer)
"""


def draw(job) -> float:
    from stereo_bench.report import plots

    start = time.process_time()
    plots._plot_job(job)
    return time.process_time() - start


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", nargs="?", type=Path, help="a run's output folder (default: the "
                                                      "paper's wide pair, run first)")
    ap.add_argument("--repeat", type=int, default=5, help="draws of each figure (default 5)")
    ap.add_argument("--baseline", metavar="REV", help="also draw the figures with git "
                                                      "revision REV and compare")
    args = ap.parse_args()
    if args.repeat < 1:
        ap.error(f"--repeat: expected a positive count, got {args.repeat}")
    if args.run is not None and not (args.run / "results.json").is_file():
        ap.error(f"{args.run}: expected a run's output folder (with results.json)")
    cv2.setNumThreads(1)
    with tempfile.TemporaryDirectory() as tmp:
        run = args.run if args.run is not None else made_run(Path(tmp) / "made")
        ours, theirs = Path(tmp) / "ours", Path(tmp) / "theirs"
        for copy in (ours, theirs):
            # The figures read the run's files and its dataset's truth, not its images.
            shutil.copytree(run, copy, ignore=shutil.ignore_patterns("plots", "images"))
        with revision_server(args.baseline, SERVER) if args.baseline else nullcontext() as base:
            measure(run, ours, theirs, args, base)


def made_run(out: Path) -> Path:
    from stereo_bench.config.schema import load_rig
    from stereo_bench.report.markdown import run_title, write_report
    from stereo_bench.run.pipeline import run

    cfg = load_rig(WIDE_PAIR)
    print(f"running {WIDE_PAIR.name} into a temporary folder ...", flush=True)
    write_report(out, run(cfg, out, ["zhang", "tsai", "bouguet", "opencv"]), run_title(cfg))
    return out


def measure(run: Path, ours: Path, theirs: Path, args, baseline) -> None:
    from stereo_bench.report import plots

    results = json.loads((run / "results.json").read_text())
    trials, agg = results["trials"], results["aggregate"]
    ds = plots._first_dataset(run, trials[0])
    figures = plots.run_figures(ds)
    best = {f: [np.inf, np.inf] for f in figures}
    for _ in range(args.repeat):
        for figure, camera in figures:
            best[figure, camera][0] = min(best[figure, camera][0],
                                          draw((str(ours), trials[0], agg, figure, camera)))
            if baseline:
                best[figure, camera][1] = min(best[figure, camera][1], baseline(
                    (str(theirs), trials[0], agg, figure, camera)))
    stages = agg["timing"]
    print(f"{run}: {len(ds.cameras)} camera(s), {ds.frames} frames; the run's stages "
          + ", ".join(f"{k.removesuffix('_s')} {v['mean']:.1f} s" for k, v in stages.items())
          + f" (sum {sum(v['mean'] for v in stages.values()):.1f} s)")
    print(f"best CPU time of {args.repeat} draws each, matplotlib on one core\n")
    header = "| figure | camera | ms |"
    if baseline:
        header += f" {args.baseline} ms | x {args.baseline} | size (px) | pixels that differ |"
    print(header)
    print("|" + " --- |" * (header.count("|") - 1))
    for (figure, camera), (now, then) in best.items():
        line = f"| {figure} | {camera or ''} | {1e3 * now:.0f} |"
        if baseline:
            size, share = compared(ours, theirs, figure, camera)
            line += f" {1e3 * then:.0f} | {now / then:.2f} | {size} | {share} |"
        print(line)
    total = sum(now for now, _ in best.values())
    line = f"| all | | {1e3 * total:.0f} |"
    if baseline:
        then = sum(then for _, then in best.values())
        line += f" {1e3 * then:.0f} | {total / then:.2f} | |"
    print(line)


def compared(ours: Path, theirs: Path, figure: str, camera: str | None) -> tuple[str, str]:
    """The two images' sizes and the share of pixels that differ (where the sizes match)."""
    name = {"projection": f"projection_difference_{camera}", "views": f"views_{camera}"}.get(
        figure, figure)
    a, b = (cv2.imread(str(folder / "plots" / f"{name}.png")) for folder in (ours, theirs))
    if a is None or b is None:
        return "not drawn", "-"
    size = f"{a.shape[1]}x{a.shape[0]}" + ("" if a.shape == b.shape
                                            else f" ({b.shape[1]}x{b.shape[0]})")
    return size, f"{(a != b).any(axis=2).mean():.1%}" if a.shape == b.shape else "-"


if __name__ == "__main__":
    main()
