"""Another git revision of this repository, run beside the working tree: the benchmarks'
``--baseline REV``.

The revision is checked out in a temporary git worktree and served by a subprocess whose
``PYTHONPATH`` puts that tree first, so that ``import stereo_bench`` there is the revision's
(the working tree's is this process's), then this folder (the benchmarks as they are now). The
subprocess runs ``code``, which answers pickled requests on stdin with pickled replies on
stdout (``serve``); the benchmark times what it asks for inside the subprocess, turn by turn
with its own work, so that both see the same load.
"""

from __future__ import annotations

import os
import pickle
import subprocess
import sys
import tempfile
from contextlib import contextmanager
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent


@contextmanager
def revision_server(rev: str, code: str):
    """A function ``ask(request) -> reply`` served by ``code`` running on revision ``rev``."""
    with tempfile.TemporaryDirectory() as tmp:
        tree = Path(tmp) / "tree"
        subprocess.run(["git", "-C", str(REPO), "worktree", "add", "--detach", "--quiet",
                        str(tree), rev], check=True)
        server = subprocess.Popen([sys.executable, "-c", code], cwd=tree,
                                  env={**os.environ,
                                       "PYTHONPATH": os.pathsep.join([str(tree), str(HERE)])},
                                  stdin=subprocess.PIPE, stdout=subprocess.PIPE)
        try:
            def ask(request):
                pickle.dump(request, server.stdin)
                server.stdin.flush()
                return pickle.load(server.stdout)
            yield ask
        finally:
            server.stdin.close()
            server.wait()
            subprocess.run(["git", "-C", str(REPO), "worktree", "remove", "--force", str(tree)],
                           check=True)


def serve(answer) -> None:
    """The subprocess's loop: each pickled request on stdin answered with ``answer(request)``,
    pickled on stdout, until stdin closes."""
    while True:
        try:
            request = pickle.load(sys.stdin.buffer)
        except EOFError:
            return
        pickle.dump(answer(request), sys.stdout.buffer)
        sys.stdout.buffer.flush()
