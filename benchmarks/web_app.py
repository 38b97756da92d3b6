"""How long `stereo-bench serve` takes to a usable page, and how large the HTML reports are.

Starts the real command on a free loopback port (as a user would) and times, from the command,
the first answer of the page (GET /) and of the example rig (GET /api/example, which loads the
rig schema), then the first preview (POST /api/preview: a frame rendered, the camera's rays
built). Then prints the size of every report.html / sweep.html under the given folders (e.g. a
`make demo` run) beside its report.md and plots. Prints, does not assert.

    python benchmarks/web_app.py [--reports out/quickstart ...] [--repeat 3]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from web_server import call, running_server  # noqa: E402 — the tests' launcher of the command


def startup(runs: Path) -> tuple[float, float, float]:
    with running_server(runs) as (url, page):
        t0 = time.perf_counter()
        call(url + "/api/example")
        ready = page + time.perf_counter() - t0
        _, example = call(url + "/api/example")
        t1 = time.perf_counter()
        status, _ = call(url + "/api/preview", {"config": example, "camera": 0, "frame": 0})
        assert status == 200, status
        return page, ready, time.perf_counter() - t1


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--reports", nargs="*", type=Path, default=[Path("out/quickstart")])
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args(argv)
    print("| start | page (s) | example rig (s) | first preview (s) |\n|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(args.repeat):
            page, ready, preview = startup(Path(tmp) / f"runs{i}")
            print(f"| {i + 1} | {page:.2f} | {ready:.2f} | {preview:.2f} |")
    print("\n| report | HTML kB | report.md kB | plots kB |\n|---|---|---|---|")
    for folder in args.reports:
        for page in sorted(folder.rglob("*.html")):
            if page.name not in ("report.html", "sweep.html"):
                continue
            md = page.with_name("sweep.md" if page.name == "sweep.html" else "report.md")
            plots = sum(p.stat().st_size for p in page.parent.glob("plots/*.png")) + sum(
                p.stat().st_size for p in page.parent.glob("*.png"))
            print(f"| {page} | {page.stat().st_size / 1e3:.0f} | "
                  f"{md.stat().st_size / 1e3 if md.exists() else 0:.0f} | {plots / 1e3:.0f} |")


if __name__ == "__main__":
    main()
