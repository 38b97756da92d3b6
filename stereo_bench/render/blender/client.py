"""A worker process (:mod:`.worker`) in the worker environment, and requests to it.

``with Worker("render") as w: w.request("board", ...)`` starts ``worker.py render`` with the
worker environment's interpreter (:func:`.environment.require`), waits for it to say it is
ready (bpy imported: about a second, paid once per worker), and sends one JSON request per
line. A failed request raises WorkerError with the worker's message; a worker that dies raises
WorkerError with the last lines it wrote to stderr. Closing ends the process.
"""

from __future__ import annotations

import collections
import json
import subprocess
import threading
from pathlib import Path

from .environment import require

WORKER = Path(__file__).with_name("worker.py")


class WorkerError(RuntimeError):
    """A request the worker could not serve, or a worker that stopped."""


class Worker:
    def __init__(self, mode: str, threads: int | None = None):
        self.mode = mode
        self.threads = threads
        self._log: collections.deque[str] = collections.deque(maxlen=30)
        self._proc = subprocess.Popen([str(require()), str(WORKER), mode], stdin=subprocess.PIPE,
                                      stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                      bufsize=1)
        # stderr is drained continuously (Blender prints a line per render tile), kept short.
        self._drain = threading.Thread(target=self._read_stderr, daemon=True)
        self._drain.start()
        self._reply()  # the worker's "ready", or why it could not start

    def _read_stderr(self):
        for line in self._proc.stderr:
            self._log.append(line.rstrip())

    def _reply(self) -> dict:
        line = self._proc.stdout.readline()
        if not line:
            self._proc.wait()
            self._drain.join(timeout=5)
            tail = "\n".join(list(self._log)[-8:])
            raise WorkerError(f"the {self.mode} worker stopped (exit {self._proc.returncode})"
                              + (f":\n{tail}" if tail else ""))
        reply = json.loads(line)
        if not reply.get("ok"):
            raise WorkerError(f"the {self.mode} worker: {reply.get('error')}")
        return reply

    def request(self, op: str, **fields) -> dict:
        if self._proc.poll() is not None:
            raise WorkerError(f"the {self.mode} worker has stopped (exit {self._proc.returncode})")
        if self.threads and "threads" not in fields:
            fields["threads"] = self.threads
        try:
            self._proc.stdin.write(json.dumps({"op": op, **fields}) + "\n")
            self._proc.stdin.flush()
        except BrokenPipeError:
            pass  # _reply reports the stopped worker with its last words
        return self._reply()

    def close(self) -> None:
        if self._proc.poll() is None:
            self._proc.stdin.close()
            try:
                self._proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self._proc.kill()
                self._proc.wait()

    def __enter__(self) -> "Worker":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
