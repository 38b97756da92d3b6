"""The analytic renderer: a textured planar board seen exactly through the camera model.

Every pixel of the distorted image looks along the ray of its undistorted normalized coordinates
(x, y, 1) (``Camera.unproject``, precomputed once per camera in :class:`PixelRays`). The ray meets
the board plane where the plane homography ``H = [r1 r2 t]`` (``cam_from_board`` restricted to
z = 0, with K = I because we work in normalized coordinates) maps board point (X, Y) to it, so
per frame the board point of every pixel is ``H^-1 (x, y, 1)``: one 3x3 matrix applied to the
precomputed coordinates, followed by a texture lookup. Rays whose plane point has negative depth
(the third component of ``H^-1 (x, y, 1)`` is 1/z) never see the board.

Anti-aliasing integrates over the pixel area like an ideal sensor (box filter, 100 % fill
factor): each pixel is the mean of ``s x s`` samples at offsets ``(k + 0.5) / s - 0.5``
(k = 0..s-1) in u and v, and each sample reads a texture rasterised (exact area coverage, by the
pattern) at texels no finer than the footprint of one sample on the board, so a bilinear read
does not alias. All filters are point-symmetric about the pixel centre, so edges and corners are
not shifted. One texture level serves the whole frame (no seams between levels), chosen for the
board's farthest, most foreshortened part; nearer parts get a coarser texture than they need,
i.e. extra symmetric blur: on the paper's trajectories the footprint varies across the board by
a factor of 1.5-1.7 in the median frame and up to 2.5, so there the texel spans up to 2.5
samples (1.25 px at s = 2).

The sample positions come from the exact per-pixel rays by bilinear interpolation of the
per-frame texel coordinates where that map is smooth (error < 1e-3 px, tests/render/test_render.py),
else of the rays themselves with the homography applied per sample (30-50 % slower). Exact rays
for every sample would cost s^2 times the memory and precomputation (1.6 GB and ~5 min at s = 4
on a 4096 x 3072 camera).

Around this ideal image sits the imaging model (imaging.py; docs/imaging.md): the lamp's
shading and highlight are painted into the frame's texture level; motion blur renders the board
at sub-frame poses over the exposure and averages them, sampling time and pixel area together:
each sub-frame reads s points of every pixel (one in each row and column of the s x s grid, a
different diagonal in consecutive sub-frames), so k sub-frames cost k s samples per pixel, not
k s^2; a board that is not its pattern (board_shape.py) is met exactly by each ray; defocus,
lens blur, vignetting and the sensor then turn the irradiance into the 8-bit image: the
optics on the board's box only (the rest is the constant background), the sensor in one
compiled pass over the box and the background around it. Without them (``clean``)
the image is computed in integers exactly as before they existed.

Conventions: millimetres, OpenCV pixel centres (top-left pixel centre = (0, 0)),
``p_cam = R @ p_board + t`` for ``cam_from_board = (R, t)``.
"""

from __future__ import annotations

import json
import math
import threading
from collections import OrderedDict
from dataclasses import dataclass

import cv2
import numpy as np

from ..core.board_shape import BoardShape
from ..core.camera import Camera, project_cam_with_jacobians
from ..core.poses import rodrigues_to_matrix, view_toward
from .imaging import (MAX_MOTION_SUBFRAMES, Light, Motion, Optics, Sensor, Surround, blinn_phong,
                      defocus, expose, vignetting_map)
from .texels import (OUTSIDE, cells_touching, grid_interpolation, inverse_2x2, noise_draws,
                     noisy_levels, offset_texels, plane_texels, sample_texels, time_area_offsets)

_PAD = 2           # background texels around every texture (also absorbs perspectiveTransform's
                   # (0, 0) answer for rays parallel to the plane)
_CELL = 32         # px, coarse grid used to find the board's image region and footprint
_OUTLINE_POINTS = 1024  # samples per outline edge when locating the board's image region
_NO_RAY = 1e7      # normalized coordinate of a pixel that sees no board: a ray 1e-7 rad off
_NO_RAY_Z = 1e-6   # the camera's plane, which meets a board 1 m away 10 km off (the background)
_TURN_DEG = 75.0   # a wide lens renders a board seen further off its axis in a turned view
_MAX_DEPTH_SLOPE = 2e-3  # per px: interpolating texel coordinates is accurate to 5e-4 px below
_LEVELS_PER_OCTAVE = 4
_LEVELS_KEPT = 4   # texture levels cached per renderer (<= 4 x 32 MiB at the default cap)
_SUBFRAME_STEP_PX = 0.5  # motion blur: the largest image motion between sub-frames
_BAND_STRIPS = 8         # motion blur: strips drawn together per sub-frame (_bands)
_SHAPE_CELL = 4          # px, grid of exact ray / warped-board intersections (see _texel_map)
_MAX_DEFOCUS_PX = 50.0   # defocus radius cap: beyond it no detector finds the board anyway


@dataclass(frozen=True)
class RenderSettings:
    """How a frame is rendered (gray levels are 8-bit units, 0..255).

    supersampling: s, the pixel is the mean of s x s samples (box filter over the pixel area).
    texel_per_sample: texture resolution policy, texel size / footprint of one sample on the
        board (largest over the visible board; 1 = mipmapping, larger blurs, smaller aliases).
    max_texture_texels: cap on the texture size (memory); beyond it the texture is coarser than the
        policy asks (blurrier, never aliased).
    background: gray level where no board is seen.
    black_level, white_level: gray levels of the board's black print and white paper under full
        light (20 / 235 leave room for noise before clipping).
    light, motion, optics, sensor: the imaging model (imaging.py); the defaults are an ideal
        camera (uniform light, no motion, a pinhole, no noise).
    board: the board as made (board_shape.py); None: exactly its pattern.
    """

    supersampling: int = 2
    texel_per_sample: float = 1.0
    max_texture_texels: int = 1 << 24
    background: float = 110.0
    black_level: float = 20.0
    white_level: float = 235.0
    light: Light = Light()
    motion: Motion = Motion()
    optics: Optics = Optics()
    sensor: Sensor = Sensor()
    board: BoardShape | None = None

    def __post_init__(self):
        def need(ok, field, expected):
            if not ok:
                raise ValueError(f"RenderSettings.{field}: expected {expected}, "
                                 f"got {getattr(self, field)!r}")

        need(isinstance(self.supersampling, (int, np.integer)) and 1 <= self.supersampling <= 16,
             "supersampling", "an integer in 1..16")
        need(self.texel_per_sample > 0, "texel_per_sample", "a positive number")
        need(self.max_texture_texels >= 1024, "max_texture_texels", "at least 1024")
        for field in ("background", "black_level", "white_level"):
            need(0 <= getattr(self, field) <= 255, field, "a gray level in 0..255")
        need(self.black_level < self.white_level, "black_level", "below white_level")
        for field, kind in (("light", Light), ("motion", Motion), ("optics", Optics),
                            ("sensor", Sensor)):
            need(isinstance(getattr(self, field), kind), field, f"an imaging.{kind.__name__}")
        light = np.asarray(self.light.direction, dtype=np.float64)
        need(light.shape == (3,) and np.all(np.isfinite(light)) and np.linalg.norm(light) > 0,
             "light", "a direction of 3 finite numbers, not all zero")

    @property
    def ideal_sensor(self) -> bool:
        """Whether the integer path serves: no motion, defocus, vignetting or photon sensor,
        only an optional Gaussian blur and additive noise (the clean and noisy presets)."""
        return not self.motion.active and \
            self.optics.f_number is None and self.optics.corner_illumination >= 1.0 and \
            self.sensor.full_well_e is None and self.sensor.gain == 1.0 and \
            self.sensor.adc_bits >= 8 and self.sensor.jpeg_quality is None


class PixelRays:
    """The per-camera precomputation: the ray of every pixel, built once per camera.

    ``xy``: (H + 2, W + 2, 2) float32, undistorted normalized coordinates of the pixel centres
    with a one-pixel margin ring, ``xy[v + 1, u + 1]`` is pixel (u, v) (the margin lets the
    sub-pixel samples of edge pixels interpolate). Computed in float64 by ``Camera.unproject``
    (Newton to 1e-10 px); float32 storage rounds by at most 3e-8 (1e-4 px at f = 3000 px).
    ``node_xy`` (h, w, 2) float64: exact rays of a coarse grid of pixels (every ``_CELL`` px,
    clamped to the image), to locate the board per frame.

    A fisheye or omnidirectional lens (lens.py) has pixels without a ray (outside its image
    circle: ``dark`` (H, W) marks them, painted black as the lens leaves them) and pixels whose
    ray points behind the camera's plane; both get a normalized coordinate far outside any
    board's image (``_NO_RAY``), so they show the background. Such a lens can see a board near
    or behind its own plane: :meth:`toward` then gives the normalized coordinates of a view
    turned toward the board (its unit rays are kept for that).
    """

    def __init__(self, camera: Camera, chunk_points: int = 1 << 15):
        self.camera = camera
        W, H = camera.width, camera.height
        self.fold_radius = camera.max_normalized_radius
        u = np.arange(-1, W + 1, dtype=np.float64)
        self.xy = np.empty((H + 2, W + 2, 2), dtype=np.float32)
        wide = camera.model != "opencv"
        # Unit rays (0 where none) of a wide lens, float32: its views toward a board (toward()).
        self.unit = np.zeros((H + 2, W + 2, 3), dtype=np.float32) if wide else None
        has_ray = np.ones((H + 2, W + 2), dtype=bool)
        rows = max(1, chunk_points // len(u))
        for r0 in range(0, H + 2, rows):
            v = np.arange(r0 - 1, min(r0 + rows, H + 2) - 1, dtype=np.float64)
            uv = np.stack(np.meshgrid(u, v), -1)
            if wide:
                rays, ok = camera.rays(uv)
                self.unit[r0:r0 + len(v)] = np.where(ok[..., None], rays, 0.0)
                self.xy[r0:r0 + len(v)], has_ray[r0:r0 + len(v)] = _normalized(rays, ok)
            else:
                self.xy[r0:r0 + len(v)] = camera.unproject(uv)
        self.dark = None if has_ray[1:-1, 1:-1].all() else ~has_ray[1:-1, 1:-1]
        nodes_u = np.minimum(np.arange(0, W - 1 + _CELL, _CELL), W - 1)
        nodes_v = np.minimum(np.arange(0, H - 1 + _CELL, _CELL), H - 1)
        nodes = np.stack(np.meshgrid(nodes_u, nodes_v), -1).astype(float)
        if wide:
            node_rays, self._node_has = camera.rays(nodes)
            self.node_unit = np.where(self._node_has[..., None], node_rays, 0.0)
            self.node_xy = _normalized(self.node_unit, self._node_has)[0]
        else:
            self.node_xy = camera.unproject(nodes)
        self._has = has_ray  # which pixels have a ray: a turned view keeps them
        self._straight = RayView(self, None, self.xy, self.node_xy)
        self._turned: RayView | None = None

    def toward(self, points_cam: np.ndarray) -> "RayView":
        """The view to render points (N, 3) (camera frame, mm; a board's outline) in: the
        camera's own, or for a wide lens that sees them more than ``_TURN_DEG`` off its axis, a
        view turned so that its axis points at their mean direction (the last one is kept,
        as motion blur's sub-frames share it)."""
        d = points_cam / np.linalg.norm(points_cam, axis=1, keepdims=True)
        if self.unit is None or d[:, 2].min() > math.cos(math.radians(_TURN_DEG)):
            return self._straight
        Q = view_toward(d.mean(0))
        if self._turned is None or not np.array_equal(self._turned.Q, Q):
            with np.errstate(invalid="ignore"):
                xy = _normalized(self.unit @ Q.T.astype(np.float32), self._has)[0]
                node_xy = _normalized(self.node_unit @ Q.T, self._node_has)[0]
            self._turned = RayView(self, Q, xy.astype(np.float32), node_xy)
        return self._turned


def _normalized(rays: np.ndarray, has_ray: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(normalized coordinates (..., 2), has a ray (...)) of unit rays (..., 3): ``_NO_RAY``
    where there is no ray or it points behind the plane."""
    ahead = has_ray & (rays[..., 2] > _NO_RAY_Z)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(ahead[..., None], rays[..., :2] / rays[..., 2:], _NO_RAY), has_ray


#: Pixel rays a process keeps (``pixel_rays``): it renders camera after camera and, as a sweep's
#: worker or the web app's preview, configuration after configuration, mostly through the same
#: few lenses; a 12 MP camera's rays take 1.3 s to build and hold 96 MiB.
MAX_KEPT_RAYS = 4
_kept_rays: OrderedDict[str, PixelRays] = OrderedDict()
_kept_rays_lock = threading.Lock()


def lens_key(camera: Camera) -> str:
    """What a camera's pixel rays depend on: its image and lens, not its name or pose."""
    lens = {k: v for k, v in camera.to_dict().items() if k not in ("name", "cam_from_world")}
    return json.dumps(lens, sort_keys=True)


def pixel_rays(camera: Camera) -> PixelRays:
    """The :class:`PixelRays` of ``camera``'s lens, built once and kept (``MAX_KEPT_RAYS``, the
    last used): a renderer takes them as they are, whichever camera of the lens built them."""
    key = lens_key(camera)
    with _kept_rays_lock:
        if key in _kept_rays:
            _kept_rays.move_to_end(key)
            return _kept_rays[key]
    rays = PixelRays(camera)
    with _kept_rays_lock:
        _kept_rays[key] = rays
        while len(_kept_rays) > MAX_KEPT_RAYS:
            _kept_rays.popitem(last=False)
    return rays


@dataclass(frozen=True)
class RayView:
    """The pixels' normalized coordinates in one view of a camera: its own frame (``Q`` None)
    or one turned by ``Q`` (view_from_cam, 3x3), where a board's pose is ``(Q R, Q t)``.
    ``xy`` and ``node_xy`` as in :class:`PixelRays`."""

    rays: PixelRays
    Q: np.ndarray | None
    xy: np.ndarray
    node_xy: np.ndarray

    @property
    def fold_radius(self) -> float:
        return self.rays.fold_radius if self.Q is None else np.inf

    def pose(self, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """view_from_board of a cam_from_board pose."""
        return (R, t) if self.Q is None else (self.Q @ R, self.Q @ t)

    def _cam_points(self, xy: np.ndarray) -> np.ndarray:
        return np.concatenate([xy, np.ones(xy.shape[:-1] + (1,))], -1) @ self.Q  # Q^T p

    def to_pixels(self, xy: np.ndarray) -> np.ndarray:
        """Pixels (N, 2) of the view's normalized coordinates xy (N, 2)."""
        cam = self.rays.camera
        return cam.normalized_to_pixels(xy) if self.Q is None else cam.project_cam(
            self._cam_points(xy))

    def jacobian(self, xy: np.ndarray) -> np.ndarray:
        """d pixels / d xy (N, 2, 2) at the view's normalized coordinates xy (N, 2)."""
        cam = self.rays.camera
        if self.Q is None:
            return cam.normalized_jacobian(xy)
        J = project_cam_with_jacobians(self._cam_points(xy), cam.intrinsics, cam.dist, True,
                                       cam.model)[1]["point"]
        return J @ self.Q.T[:, :2]


@dataclass(frozen=True)
class _Level:
    """A texture level: ``image`` (H + 2 PAD, W + 2 PAD) uint16 in 1/256 gray levels, background
    in the padding; board (X, Y) mm is at texel ``(X, Y) * px_per_mm - texel_offset``."""

    image: np.ndarray
    px_per_mm: float
    texel_offset: np.ndarray


@dataclass(frozen=True)
class _Seen:
    """The board at one pose as a view sees it: ``B`` board_from_normalized (3, 3), ``R``, ``t``
    its pose in the view, ``strips``, ``rough`` and ``footprint`` as
    :meth:`AnalyticRenderer._locate` gives them, ``front`` whether its printed front faces the
    camera."""

    B: np.ndarray
    R: np.ndarray
    t: np.ndarray
    strips: list
    rough: np.ndarray
    footprint: float
    front: bool


def _union(seen: list) -> list:
    """The strips of every pose in ``seen`` (:class:`_Seen`), united row by row (the widest
    columns, exact if any is)."""
    rows = {}
    for x in seen:
        for r0, r1, c0, c1, exact in x.strips:
            u = rows.get(r0)
            rows[r0] = (r0, r1, c0, c1, exact) if u is None else \
                (r0, r1, min(c0, u[2]), max(c1, u[3]), exact or u[4])
    return [rows[r0] for r0 in sorted(rows)]


def _bands(strips: list, rough: np.ndarray) -> list:
    """The strips merged into bands of up to ``_BAND_STRIPS`` consecutive smooth ones, each
    over their widest columns (the extra pixels see the background) and smooth only if no cell
    it spans is ``rough`` (as :meth:`AnalyticRenderer._locate` gives them): fewer, larger
    calls per sub-frame."""
    bands = []
    for r0, r1, c0, c1, exact in strips:
        if bands and not exact and not bands[-1][4] and bands[-1][1] == r0 and \
                r1 - bands[-1][0] <= _BAND_STRIPS * _CELL:
            b0, _, d0, d1, _ = bands[-1]
            c0, c1 = min(c0, d0), max(c1, d1)
            cells = rough[b0 // _CELL:-(-r1 // _CELL), c0 // _CELL:-(-c1 // _CELL)]
            bands[-1] = (b0, r1, c0, c1, bool(cells.any()))
        else:
            bands.append((r0, r1, c0, c1, exact))
    return bands


def _lagrange(nodes: np.ndarray, x: float) -> np.ndarray:
    """Weights of the values at ``nodes`` in their interpolating polynomial's value at x."""
    return np.array([np.prod([(x - m) / (n - m) for m in nodes if m != n]) for n in nodes])


class AnalyticRenderer:
    """Renders one camera's view of one board (see the module docstring for the method).

    ``camera``: the true camera (its cam_from_world only matters for the lamp of "noisy").
    ``pattern``: a board from :mod:`stereo_bench.core.patterns` (``texture(px_per_mm)``,
    ``texture_origin_mm``, ``size_mm``). ``rays``: a :class:`PixelRays` of the same lens (e.g.
    shared by clean and noisy renderers); if omitted, the process's (``pixel_rays``: built once
    per lens, the slow part).
    """

    def __init__(self, camera: Camera, pattern, settings: RenderSettings = RenderSettings(),
                 rays: PixelRays | None = None):
        if rays is not None and rays.camera is not camera and \
                lens_key(rays.camera) != lens_key(camera):
            raise ValueError("AnalyticRenderer: rays were built for another lens")
        self.camera = camera
        self.pattern = pattern
        self.settings = settings
        self.rays = rays if rays is not None else pixel_rays(camera)
        self._origin = np.asarray(pattern.texture_origin_mm, dtype=np.float64)
        self._size = np.asarray(pattern.size_mm, dtype=np.float64)
        self._levels: OrderedDict[int, _Level] = OrderedDict()
        self._vignette: np.ndarray | None = None  # built on first use (_vignetting)

    # --- public -------------------------------------------------------------------------------
    def render(self, R: np.ndarray, t: np.ndarray, rng: np.random.Generator | None = None,
               velocity: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """Image (H, W) uint8 of the board at ``cam_from_board = (R (3, 3), t (3,) mm)``.

        ``rng`` drives the sensor noise (required when the sensor is noisy): the same inputs and
        generator state give byte-identical images. ``velocity``: (omega (3,) rad/s, v (3,)
        mm/s), the board's rotation about its centre and its centre's velocity, camera frame;
        with ``settings.motion`` it is blurred over the exposure, at mid-exposure at (R, t).
        """
        st = self.settings
        if st.sensor.noisy and rng is None:
            raise ValueError("AnalyticRenderer.render: a noisy sensor needs an rng "
                             "(numpy.random.Generator)")
        R = np.asarray(R, dtype=np.float64)
        t = np.asarray(t, dtype=np.float64).reshape(-1)
        if R.shape != (3, 3) or t.shape != (3,) or not (np.all(np.isfinite(R))
                                                        and np.all(np.isfinite(t))):
            raise ValueError(f"AnalyticRenderer.render: expected finite R (3, 3) and t (3,), "
                             f"got shapes {R.shape} and {t.shape}")
        H, W = self.camera.height, self.camera.width
        poses = self._exposure_poses(R, t, velocity)
        view = self.rays.toward(self.pattern.outline_mm() @ R[:, :2].T + t)
        if len(poses) == 1:
            canvas = np.full((H, W), round(st.background * 256), dtype=np.uint16)
            strips = self._draw_board(canvas, R, t, view)
            return self._finish(self._surround(canvas), strips, rng, *view.pose(R, t), view)
        canvas, strips = self._draw_exposure(poses, view, R, t)
        return self._finish(self._surround(canvas), strips, rng, *view.pose(R, t), view)

    def _surround(self, image: np.ndarray) -> np.ndarray:
        """The image with the pixels that have no ray (a circular fisheye's surround) black."""
        if self.rays.dark is not None:
            image[self.rays.dark] = 0
        return image

    def _exposure_poses(self, R, t, velocity) -> list[tuple[np.ndarray, np.ndarray]]:
        """The sub-frame poses of the exposure: [(R, t)] without motion, else k poses at evenly
        spaced times (midpoint rule over the exposure), enough that the board's outline moves
        at most ``_SUBFRAME_STEP_PX`` between them, at least s (each sub-frame samples s
        points of every pixel's s x s grid, :meth:`_draw_exposure`) and at most
        ``MAX_MOTION_SUBFRAMES``."""
        motion = self.settings.motion
        if velocity is None or not motion.active:
            return [(R, t)]
        omega, v = (np.asarray(x, dtype=np.float64) for x in velocity)
        T = motion.exposure_ms / 1000.0
        centre_board = np.append(self.pattern.outline_centre_mm, 0.0)
        centre = R @ centre_board + t

        def pose(tau):
            dR = rodrigues_to_matrix(omega * tau)
            Rk = dR @ R
            return Rk, centre + v * tau - Rk @ centre_board

        outline = np.column_stack([self.pattern.outline_mm(), np.zeros(4)])
        ends = [(outline @ Rk.T + tk) for Rk, tk in (pose(-T / 2), pose(T / 2))]
        if min(e[:, 2].min() for e in ends) <= 0:
            steps = MAX_MOTION_SUBFRAMES  # crosses the camera's plane: as fine as allowed
        else:
            uv = [self.camera.normalized_to_pixels(e[:, :2] / e[:, 2:]) for e in ends]
            steps = int(math.ceil(np.linalg.norm(uv[1] - uv[0], axis=1).max() / _SUBFRAME_STEP_PX))
        s = self.settings.supersampling
        k = int(np.clip(steps, s, max(MAX_MOTION_SUBFRAMES, s)))
        return [pose(T * ((i + 0.5) / k - 0.5)) for i in range(k)]

    # --- geometry -----------------------------------------------------------------------------
    def _seen(self, R: np.ndarray, t: np.ndarray, view: RayView) -> "_Seen | None":
        """The board at cam_from_board (R, t) as ``view`` sees it, None when it is not seen."""
        R, t = view.pose(R, t)
        corners = self.pattern.outline_mm() @ R[:, :2].T + t
        normal_dot = R[:, 2] @ t  # > 0: the printed front faces the camera
        if corners[:, 2].max() <= 0 or abs(normal_dot) <= 1e-9 * np.linalg.norm(t):
            return None  # behind the camera, or seen exactly edge-on
        # board_from_normalized, scaled so the homogeneous w is z_ref / depth (order 1; see _PAD).
        B = np.linalg.inv(np.column_stack([R[:, 0], R[:, 1], t])) * corners[:, 2].max()
        strips, footprint, rough = self._locate(B, R, t, view)
        return _Seen(B, R, t, strips, rough, footprint, normal_dot > 0) if strips else None

    def _draw_board(self, canvas: np.ndarray, R: np.ndarray, t: np.ndarray,
                    view: RayView) -> list:
        """Render the board at cam_from_board (R, t) into ``canvas`` (H, W) uint16 through
        ``view`` (the geometry in its frame, the light in the camera's); returns the strips
        drawn."""
        seen = self._seen(R, t, view)
        if seen is None:
            return []
        s = self.settings.supersampling
        level = self._level(seen.footprint / s, front=seen.front, R=R, t=t)
        to_texels = self._texel_map(level, seen.B, seen.R, seen.t)
        border = round(self.settings.background * 256)
        for r0, r1, c0, c1, exact in seen.strips:
            xy = view.xy[r0:r1 + 2, c0:c1 + 2]  # pixels r0-1..r1, c0-1..c1
            texels = sample_texels(xy, to_texels, s, exact)
            samples = cv2.remap(level.image, texels, None, cv2.INTER_LINEAR,
                                borderMode=cv2.BORDER_CONSTANT, borderValue=border)
            canvas[r0:r1, c0:c1] = cv2.resize(samples, (c1 - c0, r1 - r0),
                                              interpolation=cv2.INTER_AREA)
        return seen.strips

    def _draw_exposure(self, poses: list, view: RayView, R: np.ndarray, t: np.ndarray
                       ) -> tuple[np.ndarray, list]:
        """The mean of the board over the exposure's sub-frame ``poses`` (time order), (H, W)
        float32 in 1/256 grey levels, and every strip drawn; (R, t) the pose at mid-exposure.

        Time and pixel area are sampled together: sub-frame i samples every pixel at the s
        area offsets :func:`time_area_offsets` gives it (one in each row and column of the
        static render's s x s grid), so k sub-frames cost k s samples per pixel and their mean
        integrates the pixel's area over the exposure (the box filter of the static render,
        swept along the motion). The texture level is the static render's
        (texels no larger than the footprint of one of its s x s samples, for the farthest
        sub-frame), lit at mid-exposure: over one exposure the shading changes to first order
        in time, which the mean over a symmetric exposure cancels. The board as made's shift
        from its plane is computed at three sub-frames and interpolated quadratically in time
        for the others (within 1e-3 px, tests/render/test_imaging.py). The sub-frames draw
        bands of the strips all of them cover (:func:`_union`, :func:`_bands`). Sums are
        integers (exact).
        """
        st = self.settings
        H, W = self.camera.height, self.camera.width
        background = round(st.background * 256)
        canvas = np.full((H, W), np.float32(background), dtype=np.float32)
        seen = [self._seen(Rk, tk, view) for Rk, tk in poses]
        drawn = [x for x in seen if x is not None]
        if not drawn:
            return canvas, []
        s = st.supersampling
        levels = {front: self._level(max(x.footprint for x in drawn if x.front == front) / s,
                                     front=front, R=R, t=t)
                  for front in {x.front for x in drawn}}
        strips = [strip for x in drawn for strip in x.strips]
        rows, cols = self._board_box(strips, 0)
        total = np.zeros((rows.stop - rows.start, cols.stop - cols.start), dtype=np.int32)
        count = np.zeros(total.shape, dtype=np.uint8)  # sub-frames that drew each pixel
        k = len(poses)
        offsets = time_area_offsets(k, s)
        maps = [None if x is None else self._texel_map(levels[x.front], x.B, x.R, x.t)
                for x in seen]
        planes = [None if x is None else plane_texels(self._homography(levels[x.front], x.B))
                  for x in seen]
        shifts = [None if x is None or self._nominal else
                  self._warp_shift(levels[x.front], x.B, x.R, x.t) for x in seen]
        # The warp's shift changes smoothly over an exposure: computed at three sub-frames and
        # interpolated (quadratic in time) for the others, when all see the same face.
        keys = [0, k // 2, k - 1] if len(drawn) == k and k > 3 and shifts[0] is not None and \
            len(levels) == 1 else None
        times = (np.arange(k) + 0.5) / k
        for r0, r1, c0, c1, exact in _bands(_union(drawn), np.bitwise_or.reduce(
                [x.rough for x in drawn])):
            xy = view.xy[r0:r1 + 2, c0:c1 + 2]  # pixels r0-1..r1, c0-1..c1
            tile = slice(r0 - rows.start, r1 - rows.start), slice(c0 - cols.start, c1 - cols.start)
            at_keys = [shifts[i](xy) for i in keys] if keys and not exact else None
            for i, x in enumerate(seen):
                if x is None or not any(a < r1 and b > r0 for a, b, *_ in x.strips):
                    continue  # nothing of the board in these rows: background
                to_texels = maps[i]
                if not exact and shifts[i] is not None:
                    texels = planes[i](xy, False)
                    if at_keys is None:
                        texels += shifts[i](xy)
                    else:
                        for w, shift in zip(_lagrange(times[keys], times[i]), at_keys):
                            cv2.scaleAdd(shift, w, texels, dst=texels)

                    def to_texels(xy, cut, texels=texels):
                        return texels
                level = levels[x.front]
                for texels in offset_texels(xy, to_texels, offsets[i], exact):
                    total[tile] += cv2.remap(level.image, texels, None, cv2.INTER_LINEAR,
                                             borderMode=cv2.BORDER_CONSTANT,
                                             borderValue=background)
                count[tile] += 1
        # Where a sub-frame drew nothing its samples are the background.
        samples = len(poses) * s
        total += (len(poses) - count.astype(np.int32)) * (s * background)
        canvas[rows, cols] = total.astype(np.float32) * np.float32(1 / samples)
        return canvas, strips

    def _texel_map(self, level: "_Level", B: np.ndarray, R: np.ndarray, t: np.ndarray):
        """A function from normalized coordinates (h, w, 2) float32 to the level's texel
        coordinates (h, w, 2) float32 (``OUTSIDE`` where the ray meets the board behind the
        camera, when ``cut`` asks for it): the plane homography for a board that is exactly its
        pattern, else the ray's intersection with the physical board (board_shape.py)."""
        plane = plane_texels(self._homography(level, B))
        if self._nominal:
            return plane
        exact = self._board_texels(level, R, t)
        shift = self._warp_shift(level, B, R, t)

        def surface(xy, cut):
            return exact(xy) if cut else plane(xy, False) + shift(xy)
        return surface

    @property
    def _nominal(self) -> bool:
        shape = self.settings.board
        return shape is None or shape.is_nominal

    @staticmethod
    def _homography(level: "_Level", B: np.ndarray) -> np.ndarray:
        """normalized (x, y) -> texel (j, i) of the level, 3x3, for board_from_normalized B."""
        A = np.array([[level.px_per_mm, 0, -level.texel_offset[0]],
                      [0, level.px_per_mm, -level.texel_offset[1]], [0, 0, 1]])
        return A @ B

    def _board_texels(self, level: "_Level", R: np.ndarray, t: np.ndarray):
        """normalized (h, w, 2) -> the level's texels where each ray meets the board as made
        at (R, t), ``OUTSIDE`` behind the camera."""
        shape = self.settings.board
        R32, t32 = R.astype(np.float32), t.astype(np.float32)
        offset = level.texel_offset.astype(np.float32)
        scale = np.float32(level.px_per_mm)

        def exact(xy):
            nominal, depth = shape.nominal_on_rays(xy, R32, t32)
            texels = nominal * scale - offset
            texels[~(depth > 0)] = OUTSIDE  # behind the camera, or parallel to the board
            return texels
        return exact

    def _warp_shift(self, level: "_Level", B: np.ndarray, R: np.ndarray, t: np.ndarray):
        """normalized (h, w, 2) of a smooth window -> the board as made's texels minus its
        plane's (h, w, 2) float32 at (R, t)."""
        exact = self._board_texels(level, R, t)
        plane = plane_texels(self._homography(level, B))

        def shift(xy):
            # The board's departure from its plane (a scale and a warp of millimetres) moves
            # texels smoothly: exact on a grid of at most _SHAPE_CELL px, bilinear in between.
            h, w = xy.shape[:2]
            rows = np.linspace(0, h - 1, -(-(h - 1) // _SHAPE_CELL) + 1).round().astype(int)
            cols = np.linspace(0, w - 1, -(-(w - 1) // _SHAPE_CELL) + 1).round().astype(int)
            coarse = np.ascontiguousarray(xy[np.ix_(rows, cols)])
            nodes = exact(coarse) - plane(coarse, False)
            # Separable linear interpolation in float (cv2.remap would round its positions to
            # 1/32 of a cell).
            return grid_interpolation(nodes, rows, cols, h, w)
        return shift

    def _locate(self, B: np.ndarray, R: np.ndarray, t: np.ndarray, view: RayView):
        """Where the board is in the image, and how large a pixel is on it.

        Works on the coarse nodes (cells of ``_CELL`` px) plus points along the outline, so
        slivers thinner than a cell are found too. Returns (strips, footprint, rough):

        * strips [(r0, r1, c0, c1, exact)]: pixel row/column ranges that contain every pixel
          seeing the board (and a margin of one cell); ``exact`` where the texel map is not
          smooth enough to interpolate: near the plane's horizon, or where rays meet the plane
          behind the camera (w <= 0), or where depth changes by more than ``_MAX_DEPTH_SLOPE``
          per pixel (interpolation error (1/4) |w'| / w px, bilinear midpoint error of a/w);
        * footprint: the largest pixel footprint on the visible board, mm per px;
        * rough: (rows, cols) uint8, the cells where the map is not smooth (and a ring around
          them), by which strips are ``exact``; None when the board is not seen.
        """
        rays, cam = view, self.camera
        H, W = cam.height, cam.width
        (x0, y0), (w, h) = self._origin, self._size
        q = np.concatenate([rays.node_xy, np.ones(rays.node_xy.shape[:-1] + (1,))], -1) @ B.T
        depth_w = q[..., 2]  # z_ref / depth along each node's ray
        with np.errstate(divide="ignore", invalid="ignore"):
            X, Y = q[..., 0] / depth_w, q[..., 1] / depth_w
            hit = (depth_w > 0) & (X >= x0) & (X <= x0 + w) & (Y >= y0) & (Y <= y0 + h)
            rough = ~(depth_w > 0)
            for axis in (0, 1):
                a, b = np.moveaxis(depth_w, axis, 0)[1:], np.moveaxis(depth_w, axis, 0)[:-1]
                steep = ~(np.abs(a - b) <= _MAX_DEPTH_SLOPE * _CELL * np.minimum(a, b))
                np.moveaxis(rough, axis, 0)[1:] |= steep
                np.moveaxis(rough, axis, 0)[:-1] |= steep
        s = np.linspace(0.0, 1.0, _OUTLINE_POINTS, endpoint=False)[:, None]
        c = self.pattern.outline_mm()
        edge = np.concatenate([c[i] + s * (c[(i + 1) % 4] - c[i]) for i in range(4)])
        pc = edge @ R[:, :2].T + t
        ahead = pc[:, 2] > 1e-9 * np.linalg.norm(t)
        exy = pc[ahead, :2] / pc[ahead, 2:]
        exy = exy[np.linalg.norm(exy, axis=1) < rays.fold_radius]
        euv = view.to_pixels(exy)
        on_img = ((euv[:, 0] > -_CELL) & (euv[:, 0] < W + _CELL)
                  & (euv[:, 1] > -_CELL) & (euv[:, 1] < H + _CELL))
        exy, euv = exy[on_img], euv[on_img]

        n_cells = (-(-H // _CELL), -(-W // _CELL))
        board = cells_touching(hit, n_cells)
        cells = np.clip(np.floor(euv / _CELL).astype(int), 0, [n_cells[1] - 1, n_cells[0] - 1])
        board[cells[:, 1], cells[:, 0]] = 1
        if not board.any():
            return [], 0.0, None
        board = cv2.dilate(board, np.ones((3, 3), np.uint8))
        # One more ring of cells for the margin pixels the interpolation reads.
        rough = cv2.dilate(cells_touching(rough, n_cells), np.ones((3, 3), np.uint8))
        strips = []
        for a in np.flatnonzero(board.any(axis=1)):
            b0, b1 = np.flatnonzero(board[a])[[0, -1]]
            strips.append((a * _CELL, min((a + 1) * _CELL, H), b0 * _CELL,
                           min((b1 + 1) * _CELL, W), bool(rough[a, b0:b1 + 1].any())))
        # The footprint varies smoothly: a sparse subset of the outline points is enough.
        footprint = self._footprint(np.concatenate([rays.node_xy[hit], exy[::16]]), B, view)
        return strips, footprint, rough

    def _footprint(self, xy: np.ndarray, B: np.ndarray, view: RayView) -> float:
        """Largest pixel footprint (mm per px) at normalized points xy (N, 2) on the board."""
        if len(xy) == 0:
            return 0.0
        q = np.concatenate([xy, np.ones((len(xy), 1))], -1) @ B.T
        # d(X, Y)/d(x, y) of the homography, then chain with d(x, y)/d(u, v) of the camera.
        J_board = (B[None, :2, :2] * q[:, 2, None, None]
                   - q[:, :2, None] * B[None, 2, None, :2]) / q[:, 2, None, None] ** 2
        J = J_board @ inverse_2x2(view.jacobian(xy))
        # Largest singular value of each 2x2, in closed form (batched SVD is 10x slower).
        frob = np.sum(J * J, axis=(1, 2))
        det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
        return float(np.sqrt(0.5 * (frob + np.sqrt(np.maximum(frob**2 - 4 * det**2, 0)))).max())

    # --- texture ------------------------------------------------------------------------------
    def _level(self, sample_mm: float, front: bool, R: np.ndarray, t: np.ndarray) -> _Level:
        """The texture level for a sample footprint of ``sample_mm``, lit and sided for the frame.

        Levels sit on a fixed grid of px_per_mm = 2^(k/4); the finest one whose texel is at
        least ``texel_per_sample * sample_mm`` is used (coarser by < 19 %: never aliased).
        """
        st = self.settings
        texel = st.texel_per_sample * max(sample_mm, 1e-9)
        cap = math.sqrt(st.max_texture_texels / float(np.prod(self._size)))
        k = math.floor(_LEVELS_PER_OCTAVE * math.log2(min(1.0 / texel, cap)))
        printed_back = not front and self.pattern.two_sided
        key = (k, printed_back)
        if key not in self._levels:
            self._levels[key] = self._rasterize(2.0 ** (k / _LEVELS_PER_OCTAVE), printed_back)
            while len(self._levels) > _LEVELS_KEPT:  # bounded memory; trajectories are smooth
                self._levels.popitem(last=False)
        self._levels.move_to_end(key)
        level = self._levels[key]
        if (front or printed_back) and st.light.uniform:
            return level
        image = level.image.copy()
        inner = image[_PAD:-_PAD, _PAD:-_PAD]
        if not front and not printed_back:  # the back of a one-sided board is blank paper
            inner[...] = round(st.white_level * 256)
        if not st.light.uniform:
            diffuse, specular = self._shading(inner.shape, R, t, front)
            if specular is None:  # one pass, rounded and saturated by OpenCV
                inner[...] = cv2.multiply(inner, diffuse, dtype=cv2.CV_16U)
            else:
                lit = cv2.multiply(inner, diffuse, dtype=cv2.CV_32F)
                lit += specular * np.float32(st.white_level * 256)
                inner[...] = np.rint(np.clip(lit, 0, 65535))  # to the nearest 1/256 level
        return _Level(image, level.px_per_mm, level.texel_offset)

    def _rasterize(self, px_per_mm: float, back: bool = False) -> _Level:
        """Board texture (``back``: the print on the back of a two-sided board, seen through it
        in the front's texel frame) at px_per_mm mapped to the gray levels, padded with
        background."""
        st = self.settings
        texture = self.pattern.back_texture if back else self.pattern.texture
        cover = texture(px_per_mm).astype(np.float32) / 255.0
        gray = (st.black_level + (st.white_level - st.black_level) * cover) * 256.0
        # The last texel column/row may reach past the outline: blend in its background share.
        for axis, size in ((1, self._size[0]), (0, self._size[1])):
            inside = size * px_per_mm - (gray.shape[axis] - 1)
            if inside < 1.0:
                edge = gray[:, -1] if axis == 1 else gray[-1]
                edge[...] = inside * edge + (1.0 - inside) * st.background * 256.0
        image = cv2.copyMakeBorder(np.rint(gray).astype(np.uint16), _PAD, _PAD, _PAD, _PAD,
                                   cv2.BORDER_CONSTANT, value=round(st.background * 256))
        # Texel (j, i) centre is at origin + (j + 0.5, i + 0.5) / px_per_mm, before padding.
        return _Level(image, px_per_mm, self._origin * px_per_mm + 0.5 - _PAD)

    def _shading(self, shape, R, t, front: bool) -> tuple[np.ndarray, np.ndarray | None]:
        """(diffuse gain, specular share), each (H, W) float32 over the level's texels
        (imaging.blinn_phong), computed on a 64 x 64 grid over the board and interpolated
        (both vary smoothly at the shininess a print has); specular None for a matte print.

        The lamp sits ``light.distance_mm`` from the world origin against its direction."""
        light, cam = self.settings.light, self.camera
        d = np.asarray(light.direction, dtype=np.float64)
        lamp = cam.R @ (-light.distance_mm * d / np.linalg.norm(d)) + cam.tvec
        n = 64
        # Grid points at the positions cv2.resize's half-pixel convention samples from.
        gx = self._origin[0] + (np.arange(n) + 0.5) * self._size[0] / n
        gy = self._origin[1] + (np.arange(n) + 0.5) * self._size[1] / n
        X, Y = np.meshgrid(gx, gy)
        p = X[..., None] * R[:, 0] + Y[..., None] * R[:, 1] + t
        normal = -R[:, 2] if front else R[:, 2]  # the seen face's normal points at the camera
        centre = R[:, :2] @ self.pattern.outline_centre_mm + t
        diffuse, specular = blinn_phong(p, normal, lamp, light, centre)
        size = (shape[1], shape[0])

        def texels(gain):
            return cv2.resize(gain.astype(np.float32), size, interpolation=cv2.INTER_LINEAR)
        return texels(diffuse), texels(specular) if light.specular > 0 else None

    # --- sensor -------------------------------------------------------------------------------
    def _finish(self, canvas: np.ndarray, strips: list, rng, R, t, view: RayView) -> np.ndarray:
        """Optics and sensor: the canvas (H, W), uint16 in 1/256 gray levels or float32 in gray
        levels (a motion-blurred mean), becomes the 8-bit image; (R, t) the board's pose in
        ``view``."""
        st = self.settings
        if st.ideal_sensor and canvas.dtype == np.uint16:
            # The exact integer path of an ideal camera (and of additive noise only).
            if st.optics.blur_px > 0 and strips:
                box = self._board_box(strips, int(math.ceil(4 * st.optics.blur_px)) + 1)
                canvas[box] = cv2.GaussianBlur(canvas[box], (0, 0), st.optics.blur_px,
                                               borderType=cv2.BORDER_REPLICATE)
            if st.sensor.noise_sigma > 0:
                return noisy_levels(rng, canvas, st.sensor.noise_sigma)
            return cv2.convertScaleAbs(canvas, alpha=1 / 256)
        # Outside the board's box the image is the uniform background, which defocus and blur
        # leave unchanged: only the box is filtered; the sensor's one pass exposes the box and
        # the (vignetted) background around it (imaging.expose).
        optics = st.optics
        H, W = canvas.shape
        reach = 0.0
        if optics.f_number is not None and strips:
            # The blur's reach from the coarse nodes, then the exact radius per pixel in the box.
            nodes = optics.circle_of_confusion_px(self._plane_depth(view.node_xy, R, t),
                                                  self.camera.fx)
            finite = np.isfinite(nodes)
            reach = min(0.5 * nodes[finite].max() if finite.any() else 0.0, _MAX_DEFOCUS_PX)
        defocus_margin = int(math.ceil(reach)) + 2 if optics.f_number is not None else 0
        blur_margin = int(math.ceil(4 * optics.blur_px)) + 1 if optics.blur_px > 0 else 0
        rows, cols = self._board_box(strips, max(defocus_margin, blur_margin)) if strips \
            else (slice(0, 0), slice(0, 0))

        def within(margin):  # the board's box widened by margin, in the region's coordinates
            r, c = self._board_box(strips, margin)
            return slice(r.start - rows.start, r.stop - rows.start), \
                slice(c.start - cols.start, c.stop - cols.start)

        region = canvas[rows, cols].astype(np.float32) * np.float32(1 / 256)  # 1/256 levels
        if optics.f_number is not None and strips:
            box = within(defocus_margin)
            xy = view.xy[rows.start + 1:rows.stop + 1, cols.start + 1:cols.stop + 1][box]
            radius = 0.5 * optics.circle_of_confusion_px(self._plane_depth(xy, R, t),
                                                         self.camera.fx)
            # A pixel of the box whose ray never meets the board's plane (a board seen nearly
            # edge-on) has no depth: the board is not there, nothing to blur.
            radius = np.where(np.isfinite(radius), radius, 0.0)
            region[box] = defocus(region[box], np.minimum(radius, reach).astype(np.float32))
        if optics.blur_px > 0 and strips:
            box = within(blur_margin)
            region[box] = cv2.GaussianBlur(region[box], (0, 0), optics.blur_px,
                                           borderType=cv2.BORDER_REPLICATE)
        vignette = self._vignetting() if optics.corner_illumination < 1.0 else None
        background = np.float32(round(st.background * 256)) * np.float32(1 / 256)
        draws = noise_draws(rng, (H, W)) if st.sensor.noisy else None
        return expose(region, st.sensor, st.white_level, draws,
                      Surround((H, W), (rows.start, cols.start), background, self.rays.dark,
                               vignette))

    def _board_box(self, strips: list, margin: int) -> tuple[slice, slice]:
        """The rows and columns of every strip drawn, widened by ``margin`` px (the rest of the
        image is uniform background, which a blur leaves unchanged)."""
        H, W = self.camera.height, self.camera.width
        r0 = max(min(s[0] for s in strips) - margin, 0)
        r1 = min(max(s[1] for s in strips) + margin, H)
        c0 = max(min(s[2] for s in strips) - margin, 0)
        c1 = min(max(s[3] for s in strips) + margin, W)
        return slice(r0, r1), slice(c0, c1)

    @staticmethod
    def _plane_depth(xy: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Depth (mm along the optical axis) where the rays of normalized coordinates xy (..., 2)
        meet the board's plane; inf where they do not (a warp's millimetres do not matter to a
        blur). In xy's precision: float32 for a frame's pixels (1e-7 of a blur's radius)."""
        n0, n1, n2 = (float(v) for v in R[:, 2])
        with np.errstate(divide="ignore", invalid="ignore"):
            depth = float(R[:, 2] @ t) / (xy[..., 0] * n0 + xy[..., 1] * n1 + n2)
        depth[~(depth > 0)] = np.inf
        return depth

    def _vignetting(self) -> np.ndarray:
        """(H, W) float32 relative illumination of each pixel (built once per renderer)."""
        if self._vignette is None:
            self._vignette = vignetting_map(self.rays.xy[1:-1, 1:-1],
                                            self.settings.optics.corner_illumination)
        return self._vignette
