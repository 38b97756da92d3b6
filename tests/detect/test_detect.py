"""Detection: found, in object_points() order, and as accurate as the image allows.

Views are clean renders (stereo_bench.render) through the paper's wide-angle camera (640 x 480,
f = (600, 450), k1 = 0.5), compared with the exact projections of the camera model.  The large-image
test warps the board texture by a homography instead (building the 4096 x 3072 camera's pixel rays
takes about a minute); its truth is the same homography.
"""

import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from stereo_bench.core.poses import rodrigues_to_matrix
from stereo_bench.config.schema import load_rig, parse_rig
from stereo_bench.scene.dataset import write_dataset
from stereo_bench.detect.dataset import (CameraDetections, DatasetDetections, detect_dataset,
                                         detection_errors)
from stereo_bench.detect.boards import detect
from stereo_bench.core.patterns import AsymmetricCircles, Charuco, Checkerboard, SymmetricCircles
from stereo_bench.render import AnalyticRenderer, PixelRays

CONFIGS = Path(__file__).resolve().parents[2] / "configs" / "paper"
# Board centre depth and offset (in board-outline diagonals: the board nearly fills the view),
# in-plane roll, then tilt about an in-plane axis at `axis` degrees.
VIEWS = [
    dict(depth=1.15, tilt=25),
    dict(depth=1.2, roll=15, tilt=30, axis=60, offset=(0.08, -0.04)),
    dict(depth=1.22, roll=-20, tilt=20, axis=135, offset=(-0.08, 0.06)),
]
ROLLED = dict(depth=1.2, roll=150, tilt=20, axis=30)


@pytest.fixture(scope="module")
def wide():
    camera = load_rig(CONFIGS / "wide_mono.yaml").cameras_true()[0]
    return camera, PixelRays(camera)


def cam_from_board(pattern, depth, roll=0.0, tilt=0.0, axis=0.0, offset=(0.0, 0.0)):
    """A pose facing the camera: board centre at (offset, depth), rolled, then tilted."""
    points = pattern.object_points()
    centre = 0.5 * (points.min(0) + points.max(0))
    a = math.radians(axis)
    R = (rodrigues_to_matrix(np.array([0.0, 0.0, math.radians(roll)]))
         @ rodrigues_to_matrix(math.radians(tilt) * np.array([math.cos(a), math.sin(a), 0.0])))
    return R, math.hypot(*pattern.size_mm) * np.array([*offset, depth]) - R @ centre


def render(wide, pattern, view):
    """Clean image and exact image points of ``pattern`` in ``view``."""
    camera, rays = wide
    R, t = cam_from_board(pattern, **view)
    truth = camera.project_cam(pattern.object_points() @ R.T + t)
    assert np.all((truth >= 0) & (truth <= [camera.width - 1, camera.height - 1])), "view setup"
    return AnalyticRenderer(camera, pattern, rays=rays).render(R, t), truth


def errors_over(pattern, detections, truths):
    """detection_errors over a list of single-image detections."""
    stacked = CameraDetections("wide", pattern.kind, "-", np.stack([d.points for d in detections]),
                               np.array([d.found for d in detections]), pattern.ids())
    truth = np.stack(truths)
    return detection_errors(stacked, truth, np.ones(truth.shape[:2], dtype=bool))


def imaged_rims(camera, R, t, pattern, scale=1.0, samples=720):
    """(N, samples, 2) image points around each disc's rim (radius times ``scale``)."""
    a = np.linspace(0.0, 2 * np.pi, samples, endpoint=False)
    rim = np.stack([np.cos(a), np.sin(a), np.zeros_like(a)], -1) * scale * pattern.diameter_mm / 2
    return camera.project_cam((pattern.object_points()[:, None] + rim) @ R.T + t)


def polygon_centroids(uv):
    """Area centroids (N, 2) of polygons (N, M, 2)."""
    x, y = uv[..., 0], uv[..., 1]
    x1, y1 = np.roll(x, -1, axis=1), np.roll(y, -1, axis=1)
    cross = x * y1 - x1 * y
    area = cross.sum(1) / 2
    moments = np.stack([((x + x1) * cross).sum(1), ((y + y1) * cross).sum(1)], -1)
    return moments / (6 * area[:, None])


# ----------------------------------------------------------------------------- accuracy
@pytest.mark.parametrize("pattern, method", [(Checkerboard(), "classic"), (Charuco(), None)])
def test_corner_boards_are_exact_to_a_twentieth_of_a_pixel(wide, pattern, method):
    detections, truths = zip(*((detect(image, pattern, method), truth)
                               for image, truth in (render(wide, pattern, v) for v in VIEWS)))
    e = errors_over(pattern, detections, truths)
    assert e["detection_rate"] == 1.0 and e["flips"] == 0
    assert e["point_detection_rate"] > 0.9  # ChArUco: nearly every corner (partial is allowed)
    assert e["mean_px"] < 0.05, e
    assert abs(e["mean_dx_px"]) < 0.01 and abs(e["mean_dy_px"]) < 0.01, e


def test_sb_checkerboard_is_found_in_order_but_less_precise(wide):
    """findChessboardCornersSB's own subpixel refinement: measured 0.067 px mean, 0.33 px max here
    (classic: 0.013, 0.047)."""
    pattern = Checkerboard()
    detections, truths = zip(*((detect(image, pattern, "sb"), truth)
                               for image, truth in (render(wide, pattern, v) for v in VIEWS)))
    e = errors_over(pattern, detections, truths)
    assert e["detection_rate"] == 1.0 and e["flips"] == 0
    assert e["mean_px"] < 0.1 and e["max_px"] < 0.5, e


@pytest.mark.parametrize("pattern", [SymmetricCircles(), AsymmetricCircles()])
def test_circle_centres_are_the_imaged_disc_centroids(wide, pattern):
    """The detector measures the centroid of each imaged disc (measured: 0.003 px mean, 0.013 px
    max); that centroid is not the image of the circle's centre, and the difference (perspective
    and lens bias: 0.04-0.05 px mean, 0.22 px max in these views) stays in the detections.
    Discs cut by the image border (the asymmetric grid's second view) are NaN rows, not biased
    centroids."""
    camera, _ = wide
    width, height = camera.width, camera.height
    detections, truths, centroids = [], [], []
    for view in VIEWS:
        image, truth = render(wide, pattern, view)
        detection = detect(image, pattern)
        pose = cam_from_board(pattern, **view)
        cut = [np.any((rim < 0) | (rim > [width - 1, height - 1]), axis=(1, 2))
               for rim in (imaged_rims(camera, *pose, pattern, scale) for scale in (1.0, 1.5))]
        missing = np.isnan(detection.points).any(axis=1)
        assert np.all(missing[cut[0]]) and not np.any(missing[~cut[1]])
        detections.append(detection)
        truths.append(truth)
        centroids.append(polygon_centroids(imaged_rims(camera, *pose, pattern)))
    to_centroids = errors_over(pattern, detections, centroids)
    to_truth = errors_over(pattern, detections, truths)
    assert to_truth["detection_rate"] == 1.0 and to_truth["flips"] == 0
    assert to_centroids["mean_px"] < 0.01 and to_centroids["max_px"] < 0.03, to_centroids
    bias = np.concatenate([c - t for c, t in zip(centroids, truths)])
    assert np.linalg.norm(bias, axis=1).max() > 0.02  # the bias is there to be kept
    assert to_truth["mean_px"] < 0.1 and to_truth["max_px"] < 0.4, to_truth


# ----------------------------------------------------------------------------- orientation
@pytest.mark.parametrize("method", ["classic", "sb"])
def test_checkerboard_order_follows_its_colours_when_rolled_150_degrees(wide, method):
    pattern = Checkerboard()
    image, truth = render(wide, pattern, ROLLED)
    e = errors_over(pattern, [detect(image, pattern, method)], [truth])
    assert e["found"] == 1 and e["flips"] == 0 and e["max_px"] < 0.5, e


def test_symmetric_grid_order_is_a_convention_and_flips_are_counted(wide):
    """No cue tells a 10 x 10 circle grid's corners apart: past 90 degrees of roll point 0 is the
    image's top-left disc, i.e. reversed against the truth, and detection_errors says so."""
    pattern = SymmetricCircles()
    image, truth = render(wide, pattern, ROLLED)
    detection = detect(image, pattern)
    e = errors_over(pattern, [detection], [truth])
    assert e["found"] == 1 and e["flips"] == 1 and e["flipped_frames"] == [0]
    assert np.linalg.norm(detection.points[::-1] - truth, axis=1).max() < 0.5
    first = detection.points[0]
    assert np.all(first <= detection.points.min(0) + 0.5 * np.ptp(detection.points, axis=0))


# ----------------------------------------------------------------------------- failures, scale
@pytest.mark.parametrize("pattern", [Checkerboard(), SymmetricCircles(), AsymmetricCircles(),
                                     Charuco()])
def test_blank_image_is_not_found_with_a_reason(pattern):
    detection = detect(np.full((480, 640), 200, np.uint8), pattern)
    n = len(pattern.object_points())
    assert not detection.found and detection.error
    assert detection.points.shape == (n, 2) and np.isnan(detection.points).all()
    assert np.array_equal(detection.ids, pattern.ids())


def test_bad_input_raises():
    with pytest.raises(ValueError, match="does not apply"):
        detect(np.zeros((10, 10), np.uint8), Charuco(), "sb")
    with pytest.raises(ValueError, match="8-bit"):
        detect(np.zeros((10, 10), np.float32), Checkerboard())


@pytest.mark.parametrize("method", ["classic", "sb"])
def test_large_image_is_searched_downscaled_and_measured_at_full_size(method):
    pattern = Checkerboard()
    px_per_mm = 14.0  # texels about the size of image pixels: a bilinear warp does not alias
    texture = cv2.GaussianBlur(pattern.texture(px_per_mm).astype(np.float32), (0, 0), 1.0)
    h, w = texture.shape
    H = (np.array([[0.9, 0.15, 900.0], [-0.1, 0.95, 250.0], [0.0, 0.0, 1.0]])
         @ np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [5e-5, 3e-5, 1.0]]))
    image = np.rint(cv2.warpPerspective(texture, H, (4096, 3072), flags=cv2.INTER_LINEAR,
                                        borderValue=110)).astype(np.uint8)
    texel = (pattern.object_points()[:, :2] - pattern.texture_origin_mm) * px_per_mm - 0.5
    truth = cv2.perspectiveTransform(texel.reshape(-1, 1, 2), H).reshape(-1, 2)
    assert truth.min() > 0 and truth[:, 0].max() < 4095 and truth[:, 1].max() < 3071
    # Speed (about 1.2 s for sb, 0.1 s for classic, against > 20 s for full-resolution SB) is
    # printed by benchmarks/detection_accuracy.py, not asserted here.
    detection = detect(image, pattern, method)
    assert detection.found
    error = np.linalg.norm(detection.points - truth, axis=1)
    assert error.mean() < 0.02 and error.max() < 0.05, (error.mean(), error.max())  # 0.007, 0.016


# ----------------------------------------------------------------------------- datasets
def test_dataset_detection_records_failures_and_round_trips(tmp_path):
    data = yaml.safe_load((CONFIGS / "wide_mono.yaml").read_text())
    data["trajectory"]["frames"] = 3
    dataset = write_dataset(parse_rig(data), tmp_path / "ds")
    missing = tmp_path / "ds" / "images" / "wide" / "000001.png"
    missing.unlink()
    calls = []
    [result] = detect_dataset(dataset, progress=lambda done, total: calls.append((done, total)))
    assert calls[-1] == (3, 3)
    assert result.points.shape == (3, 88, 2) and result.found.tolist() == [True, False, True]
    assert list(result.errors) == [1] and "000001.png" in result.errors[1]
    truth = dataset.ground_truth
    e = detection_errors(result, truth.points[0], truth.visible[0])
    assert e["found"] == 2 and e["flips"] == 0 and e["mean_px"] < 0.05

    loaded = CameraDetections.load(result.save(tmp_path / "wide"))
    assert (loaded.camera, loaded.pattern, loaded.method) == ("wide", "checkerboard", "classic")
    assert np.array_equal(loaded.points, result.points, equal_nan=True)
    assert np.array_equal(loaded.found, result.found) and loaded.errors == result.errors
    with pytest.raises(ValueError, match="not a detections file"):
        CameraDetections.load(missing)


def test_detections_taken_as_rendered_equal_those_read_back(tmp_path):
    """The run's render-to-detect path (each image detected as it is made, in this process or
    in one per camera) gives the same detections as reading the dataset's PNG files back, and
    says which image it lacks."""
    data = yaml.safe_load((CONFIGS / "wide_pair.yaml").read_text())
    data["trajectory"]["frames"] = 4
    data["pattern"] = {"kind": "charuco"}
    data["environment"] = {"kind": "noisy"}  # each frame's noise from its own generator
    cfg = parse_rig(data)
    taken = DatasetDetections(cfg.pattern.build())
    dataset = write_dataset(cfg, tmp_path / "ds", detections=taken)
    names = [c.name for c in dataset.cameras]
    for fresh, read in zip(taken.result(names, dataset.frames), detect_dataset(dataset)):
        assert fresh.found.any() and fresh.method == read.method
        assert np.array_equal(fresh.points, read.points, equal_nan=True)
        assert np.array_equal(fresh.found, read.found) and fresh.errors == read.errors
    with pytest.raises(ValueError, match="frame 4"):
        taken.result(names, dataset.frames + 1)
    # The cameras rendered and detected in two processes: the same files, the same detections.
    apart = DatasetDetections(cfg.pattern.build())
    again = write_dataset(cfg, tmp_path / "apart", detections=apart, workers=2)
    for c in names:
        for f in range(dataset.frames):
            assert (again.paths.image(c, f).read_bytes() == dataset.paths.image(c, f).read_bytes())
    assert apart.seconds > 0
    for one, two in zip(taken.result(names, 4), apart.result(names, 4)):
        assert np.array_equal(one.points, two.points, equal_nan=True)
        assert one.errors == two.errors


def test_detection_errors_counts_flips_and_keeps_them_out_of_the_statistics():
    rng = np.random.default_rng(0)
    truth = rng.uniform(0, 600, (3, 88, 2))
    offset = np.array([0.02, -0.01])
    points = truth + offset
    points[1] = points[1, ::-1]  # a 180-degree flip: reported, not repaired
    found = np.array([True, True, False])
    det = CameraDetections("c", "checkerboard", "classic", np.where(found[:, None, None], points,
                                                                     np.nan), found, np.arange(88))
    visible = np.ones((3, 88), dtype=bool)
    visible[0, :8] = False
    e = detection_errors(det, truth, visible)
    assert e["flips"] == 1 and e["flipped_frames"] == [1] and e["detection_rate"] == 2 / 3
    assert e["points"] == 80 and e["point_detection_rate"] == pytest.approx(168 / 256)
    assert e["mean_px"] == pytest.approx(np.hypot(*offset)) and e["max_px"] == pytest.approx(
        np.hypot(*offset))
    assert (e["mean_dx_px"], e["mean_dy_px"]) == pytest.approx(tuple(offset))


def test_a_corner_that_breaks_the_local_grid_is_dropped():
    from stereo_bench.detect.saddle import drop_grid_outliers
    from stereo_bench.scene.rig import Rig

    rig = Rig.from_config(load_rig(Path(__file__).resolve().parents[2] / "configs/paper/wide_mono.yaml"))
    truth = rig.ground_truth().points[0]  # (F, 88, 2) through the k1 = 0.5 lens
    obj = Checkerboard().object_points()[:, :2]
    for f in (0, 60, 126):  # near, middle and far ends of the spring
        assert np.array_equal(drop_grid_outliers(obj, truth[f], 15.0), truth[f])
        step = np.linalg.norm(truth[f, 1] - truth[f, 0])
        for i in (0, 5, 44):  # a board corner, an edge corner, an inner corner
            bad = truth[f].copy()
            # 0.3 step: what cornerSubPix did on noisy wide renders (5-6 px at 14-20 px steps)
            bad[i] += np.array([0.8, -0.6]) * 0.3 * step
            kept = drop_grid_outliers(obj, bad, 15.0)
            assert np.isnan(kept[i]).all()
            assert np.isfinite(np.delete(kept, i, axis=0)).all()


def test_markers_searched_around_the_board_are_those_of_the_whole_image():
    """detect_markers searches only the box around the pixels that differ from a uniform
    surround: the same markers, corners and order as OpenCV's search of the whole image, plain
    and with the mirrored dictionary in both polarities, for a board small in the middle, at
    each border and corner, partly off the image, large (the whole image searched), and none
    in a uniform image.  (Markers of a few pixels a cell can decode differently with the
    image's origin, in OpenCV's own search too: these are 2 px a cell or more.)"""
    from stereo_bench.detect.boards import _marker_rows, _with_mirrored_markers, detect_markers

    pattern = Charuco()
    mirrored = _with_mirrored_markers(pattern.dictionary, _marker_rows(pattern))
    texture = pattern.texture(2.0)
    th, tw = texture.shape
    board = np.float32([[0, 0], [tw, 0], [tw, th], [0, th]])
    cases = 0
    for cx, cy, scale, turn in [(960, 700, 0.9, 10), (140, 120, 0.7, -25), (1800, 1300, 0.8, 40),
                                (60, 700, 1.0, 5), (960, 1400, 0.9, 0), (960, 700, 3.2, 15),
                                (1700, 90, 0.6, 70)]:
        angle = math.radians(turn)
        spin = scale * np.array([[math.cos(angle), -math.sin(angle)],
                                 [math.sin(angle), math.cos(angle)]])
        quad = ((board - [tw / 2, th / 2]) @ spin.T + [cx, cy]).astype(np.float32)
        quad[2] += [25 * scale, -15 * scale]  # perspective
        H = cv2.getPerspectiveTransform(board, quad)
        image = cv2.warpPerspective(texture, H, (1920, 1440), flags=cv2.INTER_AREA,
                                    borderMode=cv2.BORDER_CONSTANT, borderValue=112)
        for dictionary, inverted in [(cv2.aruco.getPredefinedDictionary(
                getattr(cv2.aruco, pattern.dictionary)), False),
                (mirrored, True), ]:
            params = cv2.aruco.DetectorParameters()
            params.detectInvertedMarker = inverted
            corners, ids, _ = cv2.aruco.ArucoDetector(dictionary, params).detectMarkers(image)
            ours, our_ids = detect_markers(image, dictionary, inverted)
            assert np.array_equal(our_ids, ids) and len(ours) == len(corners)
            assert all(np.array_equal(a, b) for a, b in zip(ours, corners))
            cases += len(ids)
    assert cases > 30  # markers were found, not only their absence compared
    uniform = np.full((1440, 1920), 112, np.uint8)
    corners, ids = detect_markers(uniform, mirrored, True)
    assert corners == () and len(ids) == 0


def test_a_boards_markers_are_read_alike_by_the_first_markers_of_its_dictionary(wide):
    """The search reads only the first markers of the dictionary, up to the board's largest id:
    OpenCV takes a candidate for the first marker within the correction distance, so the
    board's markers are those the whole dictionary reads, in the same order, with the same
    corners (the wide camera's views, enlarged as the search enlarges them); a board whose ids
    lie beyond them is not read at all."""
    from stereo_bench.detect.boards import _SearchImage, _first_markers, _marker_rows

    pattern = Charuco()
    whole = pattern.aruco_dictionary()
    first = _first_markers(pattern.dictionary, _marker_rows(pattern))
    assert _marker_rows(pattern) == 54 and len(whole.bytesList) == 250
    read = 0
    for view in VIEWS:
        image = _SearchImage.of(render(wide, pattern, view)[0], 1920).image
        corners, ids, _ = cv2.aruco.ArucoDetector(whole).detectMarkers(image)
        ours, our_ids, _ = cv2.aruco.ArucoDetector(first).detectMarkers(image)
        board = [k for k, i in enumerate(ids.ravel()) if i < 54]
        assert np.array_equal(our_ids.ravel(), ids.ravel()[board])
        assert all(np.array_equal(ours[j], corners[k]) for j, k in enumerate(board))
        read += len(board)
    assert read > 100
    beyond = Charuco(marker_id_offset=54)  # ids 54-107
    image = _SearchImage.of(render(wide, beyond, VIEWS[0])[0], 1920).image
    assert len(cv2.aruco.ArucoDetector(whole).detectMarkers(image)[0]) > 30
    assert len(cv2.aruco.ArucoDetector(first).detectMarkers(image)[0]) == 0
    assert _marker_rows(Charuco(two_sided=True)) == 108
