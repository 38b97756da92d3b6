"""The web app's previews, rendered in a process of their own under a deadline.

A preview is one frame of one camera by the analytic renderer. It runs in a spawned worker
process, so that a request whose rendering runs past ``PREVIEW_SECONDS`` (a blur or defocus the
sample budget does not count) is answered with a refusal in words and the worker is killed and
replaced, instead of pinning the server; the worker keeps the per-pixel rays of the last
cameras it previewed, which is what makes the next preview of the same camera fast.
"""

from __future__ import annotations

import multiprocessing
import threading

PREVIEW_SECONDS = 30.0


class PreviewTimeout(RuntimeError):
    pass


class PreviewWorker:
    """One worker process; requests are served one at a time (a lock), in order."""

    def __init__(self, seconds: float = PREVIEW_SECONDS):
        self.seconds = seconds
        self._lock = threading.Lock()
        self._proc = None
        self._conn = None

    def _start(self) -> None:
        ctx = multiprocessing.get_context("spawn")  # a fork would copy OpenCV's thread pool
        self._conn, theirs = ctx.Pipe()
        self._proc = ctx.Process(target=_serve, args=(theirs,), daemon=True)
        self._proc.start()
        theirs.close()

    def _kill(self) -> None:
        if self._proc is not None:
            self._proc.kill()
            self._proc.join()
            self._conn.close()
        self._proc = self._conn = None

    def render(self, config: dict, camera: int, frame: int) -> tuple[bytes, dict]:
        """(PNG, headers) of the frame; ValueError with the renderer's refusal; PreviewTimeout
        past the deadline (the worker is then replaced)."""
        with self._lock:
            if self._proc is None or not self._proc.is_alive():
                self._start()
            self._conn.send((config, camera, frame))
            if not self._conn.poll(self.seconds):
                self._kill()
                raise PreviewTimeout(f"preview: camera {camera}, frame {frame} took longer than "
                                     f"{self.seconds:g} s and was stopped; lower "
                                     f"environment.supersampling, the blur or the image size")
            try:
                ok, payload = self._conn.recv()
            except EOFError:
                self._kill()
                raise ValueError(f"preview: the renderer stopped on camera {camera}, frame "
                                 f"{frame}") from None
        if not ok:
            raise ValueError(payload)
        return payload

    def close(self) -> None:
        with self._lock:
            self._kill()


def _serve(conn) -> None:
    while True:
        try:
            config, camera, frame = conn.recv()
        except EOFError:
            return
        try:
            conn.send((True, _render(config, camera, frame)))
        except ValueError as e:
            conn.send((False, str(e)))
        except Exception as e:  # noqa: BLE001 — said to the page, the worker goes on
            conn.send((False, f"preview failed: {type(e).__name__}: {e}"))


def _render(config: dict, camera: int, frame: int) -> tuple[bytes, dict]:
    from ..config.schema import parse_rig
    from ..core.files import encode_png
    from ..scene.dataset import frame_rng, render_settings
    from ..render import AnalyticRenderer
    from ..scene.rig import Rig

    cfg = parse_rig(config, "form")
    rig = Rig.from_config(cfg)
    cam = rig.cameras[camera]
    # The worker process keeps the rays of the last lenses it rendered (render.pixel_rays).
    renderer = AnalyticRenderer(cam, rig.pattern, render_settings(cfg, rig, cam))
    R, t = rig.cam_from_board(cam)
    image = renderer.render(R[frame], t[frame], frame_rng(cfg.seed, camera, frame))
    visible = int(rig.ground_truth().visible[camera, frame].sum())
    return encode_png(image), {"X-Visible-Points": str(visible), "X-Camera": cam.name,
                               "X-Frames": str(len(rig.trajectory))}
