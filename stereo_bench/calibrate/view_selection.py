"""Which of a real capture's found views a camera's intrinsics should come from: the sharp ones,
each board pose once.

A video gives views a calibration should not take as they come. A board held still is filmed
in tens of frames that repeat one pose: they add nothing but weight, so that pose outvotes the
others in the fit and in its uncertainty. A board moved by hand is smeared along its path in
some frames: the detector still finds it, but its corners move with the blur's asymmetry and the
view is noisier than the rest. So, per camera, before any method runs:

* **blur**: each view's edge spread, sigma of a Gaussian edge profile in px (``edge_spread``),
  measured at its detected points. At a corner two edges cross; for each edge direction, the
  largest gradient across it and the local contrast give sigma = contrast / (sqrt(2 pi)
  max gradient), the steepest slope of a blurred step. A view's blur is the median over its
  points of the blurrier direction, so motion blur, which smears one direction and leaves the
  other sharp, is seen. A view is left out when its blur exceeds both BLUR_FACTOR times the
  camera's median and the median plus BLUR_MARGIN_PX: a blur common to every view (defocus, a
  soft lens) leaves nothing out, only a view blurrier than the camera's own views does.
* **repeats**: views taken from the sharpest down; a view whose points lie within
  REPEAT_FRACTION of the image diagonal (RMS over the points both found) of a view already kept
  repeats its pose and is left out, naming the view it repeats.

What is left out is said per view (the capture's ``views_left_out``), and the rig still takes
every found view: a repeated frame is a moment the cameras saw together, and the rig's
bundle adjustment weighs frames, not poses.
"""

from __future__ import annotations

import numpy as np

#: A view is blurred when its edge spread is over this many times the camera's median ...
BLUR_FACTOR = 1.5
#: ... and over the median by this much, px (noise moves a sharp view's spread by a few tenths).
BLUR_MARGIN_PX = 0.5
#: A view repeats another when its points lie within this share of the image diagonal (RMS).
REPEAT_FRACTION = 0.005
#: Smoothing applied before the gradient (px), removed from the spread in quadrature: it keeps
#: the sensor's noise from passing for a steep edge.
_PRESMOOTH_PX = 0.7
#: Edge pixels whose gradient direction is within this angle of the steepest one belong to its
#: edge; those beyond _OTHER_EDGE_DEG to the other (radians, mod pi).
_SAME_EDGE = np.radians(25.0)
_OTHER_EDGE = np.radians(40.0)


def _spread_at(gx: np.ndarray, gy: np.ndarray, patch: np.ndarray) -> float:
    """The blurrier edge direction's Gaussian sigma (px) in one window around a point (the
    gradients), or NaN when the window holds no two edge directions (module notes). The contrast
    comes from ``patch``, a window twice as wide, so that a blur as wide as the gradients' window
    does not lower it."""
    contrast = float(np.percentile(patch, 95) - np.percentile(patch, 5))
    mag = np.hypot(gx, gy)
    strong = mag > 0.3 * mag.max() if mag.max() > 0 else np.zeros_like(mag, bool)
    if contrast <= 0 or strong.sum() < 6:
        return np.nan
    angle = np.arctan2(gy[strong], gx[strong]) % np.pi
    m = mag[strong]
    first = angle[np.argmax(m)]
    gap = np.abs((angle - first + np.pi / 2) % np.pi - np.pi / 2)
    same, other = m[gap < _SAME_EDGE], m[gap > _OTHER_EDGE]
    if other.size == 0:
        return np.nan
    steepest = min(same.max(), other.max())
    return contrast / (np.sqrt(2 * np.pi) * steepest)


def edge_spread(image: np.ndarray, points: np.ndarray) -> float:
    """The blur of one view (module notes): the median over its detected points (K, 2) px of the
    blurrier edge direction's Gaussian sigma, px; NaN when no point's window can tell."""
    import cv2

    pts = points[np.isfinite(points).all(axis=1)]
    if len(pts) < 2:
        return np.nan
    # A window of a third of the distance to the nearest other point: it holds the edges that
    # meet at the point and no neighbouring corner.
    d = np.linalg.norm(pts[:, None] - pts[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    half = int(np.clip(np.round(np.median(d.min(axis=1)) / 3), 3, 25))
    # Filtered over the board's bounding box only (a view's points fill a part of the image).
    pad = 2 * half + 4
    h, w = image.shape
    u0, v0 = (max(int(x) - pad, 0) for x in pts.min(axis=0))
    u1, v1 = int(min(pts[:, 0].max() + pad, w - 1)), int(min(pts[:, 1].max() + pad, h - 1))
    img = cv2.GaussianBlur(image[v0:v1 + 1, u0:u1 + 1].astype(np.float32), (0, 0), _PRESMOOTH_PX)
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    spreads = []
    for u, v in np.round(pts - [u0, v0]).astype(int):
        if not (half <= u < img.shape[1] - half and half <= v < img.shape[0] - half):
            continue  # too near the image's edge for a whole window
        win = np.s_[v - half:v + half + 1, u - half:u + half + 1]
        wide = np.s_[max(v - 2 * half, 0):v + 2 * half + 1, max(u - 2 * half, 0):u + 2 * half + 1]
        spreads.append(_spread_at(gx[win], gy[win], img[wide]))
    spreads = np.array(spreads)
    spreads = spreads[np.isfinite(spreads)]
    if spreads.size == 0:
        return np.nan
    return float(np.sqrt(max(np.median(spreads) ** 2 - _PRESMOOTH_PX ** 2, 0.0)))


def select_views(points: np.ndarray, found: np.ndarray, spreads: np.ndarray,
                 image_size: tuple[int, int], names) -> dict[int, str]:
    """The found views (frames) of one camera to leave out of its intrinsics, with the reason
    (module notes). ``points`` (F, N, 2) px, ``found`` (F,), ``spreads`` (F,) px (NaN: not
    measured, never left out for blur), ``names(frame)`` a frame's name for the reasons."""
    frames = np.flatnonzero(found)
    out: dict[int, str] = {}
    measured = spreads[frames][np.isfinite(spreads[frames])]
    if measured.size >= 3:
        median = float(np.median(measured))
        limit = max(BLUR_FACTOR * median, median + BLUR_MARGIN_PX)
        for f in frames:
            if spreads[f] > limit:
                out[int(f)] = (f"blurred: its edges spread over {spreads[f]:.2f} px (sigma), "
                               f"the camera's median view {median:.2f} px")
    radius = REPEAT_FRACTION * float(np.hypot(*image_size))
    order = sorted((f for f in frames if f not in out),
                   key=lambda f: spreads[f] if np.isfinite(spreads[f]) else np.inf)
    kept: list[int] = []
    for f in order:
        for k in kept:
            both = np.isfinite(points[f]).all(-1) & np.isfinite(points[k]).all(-1)
            if both.sum() < 4:
                continue
            rms = float(np.sqrt(np.mean(np.sum((points[f, both] - points[k, both]) ** 2, -1))))
            if rms < radius:
                out[int(f)] = (f"repeats {names(k)}'s board pose (points {rms:.1f} px RMS "
                               f"apart, under {radius:.1f} px)")
                break
        else:
            kept.append(int(f))
    return dict(sorted(out.items()))


def chosen_views(source, dets) -> tuple[list, dict[str, dict[int, str]], dict[str, dict]]:
    """Every camera's detections with the views to leave out of its intrinsics no longer marked
    found (``select_views``), those views with the reason per camera, and per camera the
    measured blur (JSON-ready: its median and each found view's, by frame name). ``source`` a
    real capture or a dataset (``image(camera, frame)``, ``frame_name``)."""
    import dataclasses

    chosen, reasons, blur = [], {}, {}
    for c, (cam, det) in enumerate(zip(source.cameras, dets)):
        spreads = np.full(len(det.found), np.nan)
        for f in np.flatnonzero(det.found):
            try:
                spreads[f] = edge_spread(source.image(c, f), det.points[f])
            except (OSError, ValueError):
                continue  # the detection read it; a second failure only costs the measure
        reasons[cam.name] = select_views(det.points, det.found, spreads, cam.size,
                                         source.frame_name)
        keep = det.found.copy()
        keep[list(reasons[cam.name])] = False
        chosen.append(dataclasses.replace(det, found=keep))
        measured = spreads[np.isfinite(spreads)]
        blur[cam.name] = {
            "edge_spread_median_px": float(np.median(measured)) if measured.size else None,
            "edge_spread_px": {source.frame_name(int(f)): float(spreads[f])
                               for f in np.flatnonzero(det.found) if np.isfinite(spreads[f])}}
    return chosen, reasons, blur


def selection_warnings(reasons: dict[str, dict[int, str]], frame_name) -> list[str]:
    """One line per camera with views left out by ``select_views``: how many as blurred and as
    repeats, the first few named."""
    out = []
    for cam, views in reasons.items():
        blurred = [frame_name(f) for f, r in views.items() if r.startswith("blurred")]
        repeats = [frame_name(f) for f, r in views.items() if r.startswith("repeats")]
        parts = [f"{len(names)} as {what} ({', '.join(names[:4])}"
                 f"{', ...' if len(names) > 4 else ''})"
                 for names, what in ((blurred, "blurred"),
                                     (repeats, "repeating a board pose already taken")) if names]
        if parts:
            out.append(f"camera {cam!r}: {' and '.join(parts)} left out of its intrinsics "
                       f"(the rig still uses them; results.json's views_left_out says why each)")
    return out
