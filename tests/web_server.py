"""`stereo-bench serve` started as a user starts it, on a free loopback port, for the web tests
and benchmarks/web_load.py; and a plain HTTP client for its API."""

from __future__ import annotations

import contextlib
import json
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextlib.contextmanager
def running_server(runs):
    """(base URL, seconds from the command to a page that answers); the server is stopped
    after."""
    port = free_port()
    start = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-m", "stereo_bench.cli", "serve", "--runs",
                             str(runs), "--port", str(port)], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    url = f"http://127.0.0.1:{port}"
    try:
        while True:
            try:
                with urllib.request.urlopen(url + "/", timeout=1) as r:
                    if r.status == 200:
                        break
            except (urllib.error.URLError, ConnectionError, TimeoutError):
                pass
            if proc.poll() is not None:
                raise RuntimeError(f"serve stopped: {proc.stdout.read()}")
            if time.perf_counter() - start > 60:
                raise RuntimeError("serve did not answer within 60 s")
            time.sleep(0.1)
        yield url, time.perf_counter() - start
    finally:
        proc.terminate()
        proc.wait(timeout=20)


def call(url: str, body=None, method: str | None = None, headers=None, raw: bytes | None = None,
         timeout: float = 120):
    """(status, parsed JSON or the bytes of another answer) of one request."""
    data = raw if raw is not None else (None if body is None else json.dumps(body).encode())
    request = urllib.request.Request(url, data, {"Content-Type": "application/json",
                                                 **(headers or {})}, method=method)
    try:
        with urllib.request.urlopen(request, timeout=timeout) as r:
            status, content, kind = r.status, r.read(), r.headers.get("Content-Type", "")
    except urllib.error.HTTPError as e:
        status, content, kind = e.code, e.read(), e.headers.get("Content-Type", "")
    return status, json.loads(content) if "json" in kind else content
