"""aniposelib's calibration, as anipose runs it: ``CameraGroup.calibrate_rows`` on each camera's
rows of detected board points, with anipose's default cameras (``Camera(size=...)``: one focal
length fx = fy, the principal point at the image's centre, k1 its only distortion), its own
initialization (cv2.initCameraMatrix2D, a pose per view with solvePnPRansac, a tree of camera
pairs) and its bundle adjustment. The board: aniposelib's ``Checkerboard`` (views of the whole
board only: it poses nothing else) or ``CharucoBoard`` (partial views, with their corner ids).
The answer is ``CameraGroup.dump``'s calibration.toml, read back with io.anipose.

aniposelib draws random samples (its pose initialization, its point subsets) from numpy's
global generator: it is seeded with 0 before the call so that a rerun gives the same answer.
"""

from __future__ import annotations

import contextlib
import io
import time
from pathlib import Path

import numpy as np

from ..io import anipose as anipose_file
from . import Session, ToolError, ToolResult

ABOUT = ("aniposelib 0.8 CameraGroup.calibrate_rows with anipose's default cameras (fx = fy, "
         "centred principal point, k1)")


def missing() -> str | None:
    try:
        import aniposelib  # noqa: F401
        import jax  # noqa: F401  (its triangulation imports it)
    except ImportError as e:
        return f"aniposelib cannot be imported ({e}); `make venv` installs it with jax"
    return None


def _board(session: Session):
    from aniposelib.boards import CharucoBoard, Checkerboard

    pattern = session.pattern
    if pattern.kind == "charuco":
        parts = pattern.dictionary.split("_")  # DICT_<bits>X<bits>_<count>
        if (len(parts) != 3 or not parts[2].isdigit() or pattern.legacy
                or pattern.marker_id_offset or pattern.two_sided):
            raise ToolError(f"anipose: aniposelib's CharucoBoard takes a DICT_<n>X<n>_<count> "
                            f"dictionary from marker 0, not this board's ({pattern.dictionary}, "
                            f"legacy {pattern.legacy}, offset {pattern.marker_id_offset}, "
                            f"two-sided {pattern.two_sided})")
        board = CharucoBoard(pattern.squares_x, pattern.squares_y, pattern.square_mm,
                             pattern.marker_mm, marker_bits=int(parts[1].split("X")[0]),
                             dict_size=int(parts[2]))
    elif pattern.kind == "checkerboard":
        cols, rows, spacing = session.grid()
        board = Checkerboard(cols, rows, square_length=spacing)
    else:
        raise ToolError(f"anipose: aniposelib has no {pattern.kind} board (checkerboard and "
                        f"charuco only)")
    # The same corners in the same order, up to where the board's frame starts.
    obj = board.get_object_points()
    if obj.shape != session.object_points.shape or not np.allclose(
            obj - obj[0], session.object_points - session.object_points[0], atol=1e-6):
        raise ToolError(f"anipose: aniposelib numbers the {pattern.kind}'s corners otherwise")
    return board


def _rows(session: Session, c: int, partial: bool) -> list[dict]:
    rows = []
    for f in np.flatnonzero(session.found[c]):
        ok = np.isfinite(session.image_points[c, f]).all(-1)
        if not ok.any() or (not partial and not ok.all()):
            continue
        ids = np.flatnonzero(ok).astype(np.int32)
        rows.append({"framenum": int(f),
                     "corners": session.image_points[c, f, ok].reshape(-1, 1, 2)
                     .astype(np.float32),
                     "ids": ids.reshape(-1, 1) if partial else ids})
    return rows


def calibrate(session: Session, out_dir: Path, name: str = "anipose") -> ToolResult:
    from aniposelib.cameras import Camera, CameraGroup

    if len(session.names) < 2:
        raise ToolError("anipose: calibrate_rows calibrates a group of two or more cameras")
    board = _board(session)
    partial = session.pattern.kind == "charuco"
    group = CameraGroup([Camera(name=n, size=s) for n, s in zip(session.names, session.sizes)])
    rows = [_rows(session, c, partial) for c in range(len(session.names))]
    np.random.seed(0)
    t0 = time.perf_counter()
    said = io.StringIO()
    try:
        with contextlib.redirect_stdout(said):
            error = group.calibrate_rows(rows, board, init_intrinsics=True, init_extrinsics=True,
                                         verbose=False)
    except (ValueError, IndexError, KeyError, np.linalg.LinAlgError) as e:
        raise ToolError(f"anipose: calibrate_rows failed: {type(e).__name__}: {e}") from None
    elapsed = time.perf_counter() - t0
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / anipose_file.FILE
    group.dump(str(path))
    cams = [c.with_params(name=n) for c, n in zip(anipose_file.read(path), session.names)]
    return ToolResult(cams, path, "anipose", elapsed,
                      {"reported_error_px": float(error), "rows": [len(r) for r in rows]})
