"""The Blender backend for boards: the same interface, poses and ground truth as the analytic one.

``BlenderRenderer(camera, pattern, settings, worker, workdir).render(R, t, rng)`` sends the pose
to a render worker (:mod:`.client`), which renders the pinhole view (:mod:`.lens`) of a matte
plane carrying the board's texture with Cycles; the package then applies the camera's lens
(one exact remap) and the rest of the imaging model that is not light: the Gaussian lens blur,
vignetting and the sensor (``imaging.photograph``, the same photon transfer, noise and ADC as the
analytic backend). Defocus is Blender's own thin lens (the sensor is as wide as the lens and
the pixel pitch make it).

Light: ``light.ambient`` 1 (``clean``) is an emission shader, so each pixel is the exact mean of
the print's grey levels over its area (a box pixel filter, ``samples`` per pixel); otherwise
(``noisy``) a diffuse print under a sun travelling along ``light.direction`` plus uniform
ambient light, the grey level ``rho ((1 - ambient) cos + ambient)``. The analytic lamp stands at
a finite distance (its shading varies over the board); the sun does not. Values travel as linear
16-bit PNG (Blender's Raw view), 1/257 grey level steps.

Cycles renders only the board's region of the pinhole image (``BlenderRenderer._region``); the
rest is the background grey camera rays see there, the same pixels the whole frame would have.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ...core.camera import Camera
from ...core.files import write_png
from ..analytic import PixelRays, RenderSettings, pixel_rays
from ..imaging import camera_vignette, photograph
from .client import Worker
from .lens import PinholeView

MAX_TEXTURE_SIDE = 8192
_LEVELS = 65535.0
# Pixels rendered beyond the board's outline: the box pixel filter's half pixel, Blender's
# rounding of the region to whole pixels, and the bilinear taps of the lens remap.
REGION_MARGIN_PX = 4


def texture_density(camera: Camera, pattern, R: np.ndarray, t: np.ndarray) -> float:
    """Texels per mm for ``pattern`` seen by ``camera`` at the poses (R (F, 3, 3), t (F, 3)):
    twice the most pixels per mm any pose shows (texels under half a pixel, so the texture's
    bilinear interpolation adds no blur a pixel would see), capped so the texture's longest
    side stays at ``MAX_TEXTURE_SIDE``."""
    outline = np.column_stack([pattern.outline_mm(), np.zeros(4)])
    depth = np.einsum("fij,nj->fni", R, outline)[..., 2] + t[:, None, 2]
    near = depth[depth > 0].min() if np.any(depth > 0) else 1000.0
    wanted = 2.0 * max(camera.fx, camera.fy) / near
    return float(min(max(wanted, 4.0), MAX_TEXTURE_SIDE / max(pattern.size_mm)))


class BlenderRenderer:
    """Renders one camera's view of one board through a render worker (see the module notes).

    ``workdir``: a folder inside the output where the texture and the pinhole frame go.
    ``px_per_mm``: the texture's density (:func:`texture_density`); ``samples`` per pixel at
    most, ``noise_threshold`` Cycles' adaptive sampling (0: off; RendererConfig).
    """

    def __init__(self, camera: Camera, pattern, settings: RenderSettings, worker: Worker,
                 workdir: Path, px_per_mm: float = 20.0, samples: int = 64,
                 rays: PixelRays | None = None, noise_threshold: float = 0.0):
        self.camera, self.pattern, self.settings, self.worker = camera, pattern, settings, worker
        rays = rays if rays is not None else pixel_rays(camera)
        self.view = PinholeView.of(camera, rays)
        self._vignette = camera_vignette(rays.xy[1:-1, 1:-1], settings.optics)
        self._frame = Path(workdir) / f"{camera.name}_pinhole.png"
        texture_path = Path(workdir) / f"{camera.name}_texture.png"
        st = settings
        cover = pattern.texture(px_per_mm).astype(np.float64) / 255.0
        levels = st.black_level + (st.white_level - st.black_level) * cover
        write_png(texture_path, np.rint(levels / 255.0 * _LEVELS).astype(np.uint16))
        h, w = cover.shape
        x0, y0 = np.asarray(pattern.texture_origin_mm, float)
        extent = [x0 / 1000, y0 / 1000, (x0 + w / px_per_mm) / 1000, (y0 + h / px_per_mm) / 1000]
        light = None
        if not st.light.uniform:
            # The world frame of a board scene is this camera's (OpenCV axes).
            light = {"direction": (camera.R @ np.asarray(st.light.direction, float)).tolist(),
                     "ambient": st.light.ambient}
        o = st.optics
        worker.request("board", samples=samples, noise_threshold=noise_threshold,
                       texture=str(texture_path), extent_m=extent,
                       camera=self.view.spec(in_world=False, f_number=o.f_number,
                                             focal_length_mm=o.focal_length_mm,
                                             focus_mm=o.focus_distance_mm),
                       background=st.background / 255.0, light=light)

    def render(self, R: np.ndarray, t: np.ndarray, rng: np.random.Generator | None = None,
               velocity=None) -> np.ndarray:
        """Image (H, W) uint8 of the board at ``cam_from_board = (R, t mm)``; ``velocity`` is
        accepted for the interface and unused (the rig file refuses motion blur here)."""
        st = self.settings
        if st.sensor.noisy and rng is None:
            raise ValueError("BlenderRenderer.render: a noisy sensor needs an rng")
        M = np.eye(4)
        M[:3, :3] = np.asarray(R, float)
        M[:3, 3] = np.asarray(t, float).reshape(3) / 1000.0
        region = self._region(M[:3, :3], M[:3, 3] * 1000.0)
        # Blender rounds a region's fractional bounds to whole pixels its own way (a row short,
        # measured): it is asked for one pixel more on every side than is kept (the image's
        # own edges, 0 and 1 as fractions, are exact).
        pin = self.view.pinhole
        asked = None if region is None else [max(region[0] - 1, 0), max(region[1] - 1, 0),
                                             min(region[2] + 1, pin.width),
                                             min(region[3] + 1, pin.height)]
        self.worker.request("board_frame", cam_from_board=M.tolist(), out=str(self._frame),
                            region=asked)
        pinhole = cv2.imread(str(self._frame), cv2.IMREAD_UNCHANGED)
        if pinhole is None or pinhole.dtype != np.uint16:
            raise RuntimeError(f"{self._frame}: the render worker wrote no 16-bit image")
        if region is not None:
            # Outside the region every camera ray sees the world's grey, which Blender's film
            # holds exactly and writes rounded to 16 bits.
            x0, y0, x1, y1 = region
            inside = pinhole[y0:y1, x0:x1].copy()
            pinhole[...] = round(st.background / 255.0 * _LEVELS)
            pinhole[y0:y1, x0:x1] = inside
        grey = pinhole.astype(np.float32) * np.float32(255.0 / _LEVELS)
        image = self.view.distort(grey, border=st.background)
        # Blender's camera made the defocus; the rest of the camera is the suite's.
        return photograph(image, st.optics, st.sensor, st.white_level, self._vignette, rng)

    def _region(self, R: np.ndarray, t: np.ndarray) -> list[int] | None:
        """The pinhole image's pixels [x0, y0, x1, y1] (ends exclusive) the board at (R, t mm)
        can reach: its outline's bounding box, widened by ``REGION_MARGIN_PX`` and the radius
        of Blender's defocus at the outline's depths; None (the whole image) when the board
        reaches the camera's plane. Cycles then renders only the board's pixels: the paper's
        spring fills a fraction of the 4096 x 3072 frame."""
        corners = self.pattern.outline_mm() @ R[:, :2].T + t
        if corners[:, 2].min() <= 1.0:
            return None
        pin = self.view.pinhole
        uv = corners[:, :2] / corners[:, 2:] * [pin.fx, pin.fy] + [pin.cx, pin.cy]
        margin = REGION_MARGIN_PX
        if self.settings.optics.f_number is not None:
            margin += 0.5 * float(np.max(self.settings.optics.circle_of_confusion_px(
                corners[:, 2], pin.fx)))
        lo = np.floor(uv.min(0) - margin).astype(int)
        hi = np.ceil(uv.max(0) + margin).astype(int) + 1
        lo, hi = np.maximum(lo, 0), np.minimum(hi, [pin.width, pin.height])
        if np.any(hi <= lo):
            return None
        return [int(lo[0]), int(lo[1]), int(hi[0]), int(hi[1])]

    def close(self) -> None:
        """Remove the scratch frame (the texture stays: it is what was rendered)."""
        self._frame.unlink(missing_ok=True)
