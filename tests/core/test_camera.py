"""The camera core against OpenCV, finite differences and round trips."""

import cv2
import numpy as np
import pytest

from stereo_bench.core.camera import Camera, project_with_jacobians
from stereo_bench.core.distortion import DistortionNotInvertibleError
from stereo_bench.core.poses import matrix_to_rodrigues, rodrigues_to_matrix
from stereo_bench.io import opencv_yaml

RECTILINEAR = Camera("rect", 4096, 3072, 3000, 3000, 2048, 1536, 0,
                     np.array([0.05, 0.02, 0.001, 0, 0, 0, 0, 0]))
WIDE = Camera("wide", 640, 480, 600, 450, 320, 240, 0,
              np.array([0.5, 0.1, 0.03, 0, 0, 0, 0, 0]))


def random_camera(rng, rational=True):
    w, h = int(rng.integers(320, 4096)), int(rng.integers(240, 3072))
    d = np.concatenate([rng.normal(0, [0.1, 0.05, 0.003, 0.003, 0.01]),
                        rng.normal(0, [0.05, 0.02, 0.01]) if rational else np.zeros(3)])
    return Camera("r", w, h, rng.uniform(300, 3000), rng.uniform(300, 3000),
                  w / 2 + rng.normal(0, 20), h / 2 + rng.normal(0, 20), 0.0, d,
                  rng.normal(0, 0.5, 3), rng.normal(0, 50, 3))


def random_points(rng, cam, n=200):
    # Points in front of the camera within a modest field of view, then to world.
    pc = np.stack([rng.uniform(-0.4, 0.4, n), rng.uniform(-0.4, 0.4, n), np.ones(n)], -1)
    pc *= rng.uniform(200, 3000, (n, 1))
    return (pc - cam.tvec) @ cam.R  # world = R^T (pc - t)


def test_projection_matches_opencv():
    rng = np.random.default_rng(0)
    worst = 0.0
    for _ in range(20):
        cam = random_camera(rng)
        X = random_points(rng, cam)
        ours = cam.project(X)
        ref, _ = cv2.projectPoints(X, cam.rvec, cam.tvec, cam.K, cam.dist)
        worst = max(worst, np.abs(ours - ref.reshape(-1, 2)).max())
    assert worst < 1e-9


def test_rodrigues_matches_opencv_and_inverts():
    rng = np.random.default_rng(1)
    rv = np.concatenate([rng.normal(0, 1, (50, 3)), [[0, 0, 0], [1e-10, 0, 0]],
                         [[np.pi - 1e-9, 0, 0]], rng.normal(0, 1, (5, 3)) * 1e-5])
    for v in rv:
        assert np.abs(rodrigues_to_matrix(v) - cv2.Rodrigues(v)[0]).max() < 1e-12
        R = rodrigues_to_matrix(v)
        assert np.abs(rodrigues_to_matrix(matrix_to_rodrigues(R)) - R).max() < 1e-10


@pytest.mark.parametrize("seed", range(5))
def test_jacobians_match_finite_differences(seed):
    rng = np.random.default_rng(seed)
    cam = random_camera(rng)
    cam = cam.with_params(skew=rng.normal(0, 2))
    X = random_points(rng, cam, 30)
    intr, dist, rv, tv = cam.intrinsics, cam.dist, cam.rvec, cam.tvec
    _, J = project_with_jacobians(X, intr, dist, rv, tv)

    def fd(f, x0, h):
        cols = []
        for i in range(len(x0)):
            e = np.zeros_like(x0)
            e[i] = h[i] if np.ndim(h) else h
            cols.append((f(x0 + e) - f(x0 - e)) / (2 * e[i]))
        return np.stack(cols, -1)

    def proj(i=intr, d=dist, r=rv, t=tv, P=X):
        return project_with_jacobians(P, i, d, r, t, jacobians=False)[0]

    checks = {
        "intrinsics": fd(lambda p: proj(i=p), intr, 1e-4),
        "dist": fd(lambda p: proj(d=p), dist, 1e-7),
        "pose": fd(lambda p: proj(r=p[:3], t=p[3:]), np.concatenate([rv, tv]),
                   np.array([1e-7] * 3 + [1e-4] * 3)),
    }
    for name, num in checks.items():
        rel = np.abs(J[name] - num).max() / np.abs(num).max()
        assert rel < 1e-6, (name, rel)
    for k in range(len(X)):
        num = fd(lambda p: proj(P=p[None])[0], X[k], 1e-4)
        rel = np.abs(J["point"][k] - num).max() / np.abs(num).max()
        assert rel < 1e-6, ("point", rel)


def test_rotation_jacobian_near_identity():
    X = np.array([[10.0, -20.0, 500.0]])
    intr = np.array([800, 800, 320, 240, 0.0])
    for rv in (np.zeros(3), np.array([1e-9, -2e-9, 0.0])):
        _, J = project_with_jacobians(X, intr, np.zeros(8), rv, np.zeros(3))
        h = 1e-7
        num = np.stack([(project_with_jacobians(X, intr, np.zeros(8), rv + h * e, np.zeros(3),
                                                False)[0]
                         - project_with_jacobians(X, intr, np.zeros(8), rv - h * e, np.zeros(3),
                                                  False)[0])[0] / (2 * h) for e in np.eye(3)], -1)
        assert np.abs(J["pose"][0, :, :3] - num).max() / np.abs(num).max() < 1e-6


@pytest.mark.parametrize("cam", [RECTILINEAR, WIDE], ids=["rectilinear", "wide"])
def test_unproject_roundtrip_whole_image(cam):
    uv = np.concatenate([cam.pixel_grid(7).reshape(-1, 2),
                         [[0, 0], [cam.width - 1, cam.height - 1], [cam.width - 1, 0]]])
    xy = cam.unproject(uv)
    back = cam.normalized_to_pixels(xy)
    assert np.abs(back - uv).max() < 1e-9


def test_unproject_roundtrip_random_cameras():
    rng = np.random.default_rng(3)
    for _ in range(10):
        cam = random_camera(rng, rational=False)
        X = random_points(rng, cam, 500)
        uv = cam.project(X)
        xy = cam.unproject(uv)
        Pc = cam.world_to_cam(X)
        assert np.abs(xy - Pc[:, :2] / Pc[:, 2:]).max() < 1e-9


def test_unproject_refuses_fold():
    # k1 < 0 strong enough that r(1 + k1 r^2) folds inside the image.
    cam = Camera("folded", 640, 480, 300, 300, 320, 240, 0, np.array([-0.6, 0, 0, 0, 0]))
    with pytest.raises(DistortionNotInvertibleError, match="folded"):
        cam.check_invertible()
    WIDE.check_invertible()
    RECTILINEAR.check_invertible(step=64)


def test_json_and_opencv_yaml_roundtrip(tmp_path):
    cam = RECTILINEAR.with_params(rvec=np.array([0.1, -0.2, 0.3]), tvec=np.array([1, 2, 3.0]),
                                  skew=0.5)
    cam.save_json(tmp_path / "c.json")
    opencv_yaml.write_camera(cam, tmp_path / "c.yaml")
    for back in (Camera.load_json(tmp_path / "c.json"),
                 opencv_yaml.read_camera(tmp_path / "c.yaml")):
        assert back.name == cam.name and back.size == cam.size
        assert np.array_equal(back.K, cam.K) and np.array_equal(back.dist, cam.dist)
        assert np.array_equal(back.rvec, cam.rvec) and np.array_equal(back.tvec, cam.tvec)


def test_bad_camera_input_names_the_field(tmp_path):
    with pytest.raises(ValueError, match="fx and fy"):
        Camera("c", 10, 10, -1, 1, 0, 0)
    p = tmp_path / "bad.json"
    p.write_text('{"name": "c", "width": 10}')
    with pytest.raises(ValueError, match="bad.json.*height"):
        Camera.load_json(p)


def test_nearest_rotation_and_geodesic_distance():
    from stereo_bench.core.poses import geodesic_distance, nearest_rotation

    rng = np.random.default_rng(5)
    R = rodrigues_to_matrix(rng.normal(0, 1, (20, 3)))
    assert np.abs(nearest_rotation(R + rng.normal(0, 1e-9, R.shape)) - R).max() < 1e-8
    # A reflection is projected onto a proper rotation (det +1), not kept.
    assert np.allclose(np.linalg.det(nearest_rotation(-R)), 1.0)
    small = rodrigues_to_matrix(np.array([1e-9, 0, 0]))
    assert abs(geodesic_distance(np.eye(3), small) - 1e-9) < 1e-20
    axis = np.array([0.0, 0.6, 0.8])
    assert np.isclose(geodesic_distance(R[0], R[0] @ rodrigues_to_matrix(axis * 2.5)), 2.5)
