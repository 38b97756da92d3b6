"""`stereo-bench serve` under a bounded load on loopback, with a job running, then cancelled.

Starts the real command (as a user would), starts a long run (the quick-start rig at 400
frames), and while it computes sends ``--clients`` concurrent clients, each making
``--requests`` requests alternating POST /api/validate, POST /api/preview (a frame of the
quick-start rig) and GET /api/jobs/{id}. Prints the latency percentiles per kind of request
beside the same requests with no job running, how many answers were not 200, and then the
time from POST /api/jobs/{id}/cancel to the job's state reading "cancelled". Prints, does not
assert.

    python benchmarks/web_load.py [--clients 8] [--requests 30]
"""

from __future__ import annotations

import argparse
import copy
import sys
import tempfile
import time
from collections import defaultdict
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from web_server import call, running_server  # noqa: E402 — the tests' launcher of the command


def load(url: str, example: dict, job_id: int | None, clients: int, requests: int) -> dict:
    kinds = [("validate", "/api/validate", {"config": example}),
             ("preview", "/api/preview", {"config": example, "camera": 0, "frame": 2})]
    if job_id is not None:
        kinds.append(("job", f"/api/jobs/{job_id}", None))

    def client(c: int):
        seen = []
        for r in range(requests):
            kind, path, body = kinds[(c + r) % len(kinds)]
            t = time.perf_counter()
            status, _ = call(url + path, body)
            seen.append((kind, time.perf_counter() - t, status))
        return seen

    times, bad = defaultdict(list), 0
    with ThreadPoolExecutor(clients) as pool:
        for seen in pool.map(client, range(clients)):
            for kind, seconds, status in seen:
                times[kind].append(seconds)
                bad += status != 200
    return {"times": times, "not_ok": bad}


def table(label: str, result: dict) -> None:
    for kind, seconds in sorted(result["times"].items()):
        ms = 1000 * np.array(seconds)
        print(f"| {label} | {kind} | {len(ms)} | {np.percentile(ms, 50):.0f} | "
              f"{np.percentile(ms, 90):.0f} | {np.percentile(ms, 99):.0f} | {ms.max():.0f} |")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--clients", type=int, default=8)
    parser.add_argument("--requests", type=int, default=30)
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp, running_server(Path(tmp) / "runs") as (url, _):
        _, example = call(url + "/api/example")
        call(url + "/api/preview", {"config": example, "camera": 0, "frame": 2})  # warm rays
        idle = load(url, example, None, args.clients, args.requests)
        rig = copy.deepcopy(example)
        rig["trajectory"]["frames"] = 400
        _, job = call(url + "/api/runs", {"name": "busy", "config": rig})
        while call(f"{url}/api/jobs/{job['id']}")[1]["done"] == 0:
            time.sleep(0.1)
        busy = load(url, example, job["id"], args.clients, args.requests)
        state = call(f"{url}/api/jobs/{job['id']}")[1]
        t = time.perf_counter()
        call(f"{url}/api/jobs/{job['id']}/cancel", method="POST")
        while call(f"{url}/api/jobs/{job['id']}")[1]["state"] == "running":
            time.sleep(0.02)
        stopped = time.perf_counter() - t
    print(f"{args.clients} concurrent clients x {args.requests} requests each, loopback\n")
    print("| load | request | n | p50 ms | p90 ms | p99 ms | max ms |\n|---|---|---|---|---|---|---|")
    table("idle", idle)
    table("job running", busy)
    print(f"\nanswers other than 200: idle {idle['not_ok']}, job running {busy['not_ok']}")
    print(f"the job was at {state['stage']} {state['done']}/{state['total']} when the load ended; "
          f"cancelled -> state 'cancelled' in {stopped:.2f} s")


if __name__ == "__main__":
    main()
