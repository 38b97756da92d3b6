"""Exchange formats: every writer's files read back by its reader and by the real tool's library
(cv2.FileStorage + cv2.projectPoints / cv2.fisheye / cv2.omnidir, pycolmap, aniposelib,
caliscope, mrcal where a Python with it is found; Kalibr, which has no Python package, through
its C++ formulas), projections of random 3D points agreeing to 1e-9 px, for every lens model a
format carries; the refusals; malformed files."""

import ast
import re
import subprocess
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from stereo_bench import io as formats
from stereo_bench.core.camera import Camera
from stereo_bench.core.poses import look_at_rotation, matrix_to_rodrigues, rodrigues_to_matrix
from stereo_bench.io import anipose, caliscope, colmap, easymocap, kalibr, mrcal, opencv_yaml

TOL_PX = 1e-9
TARGET = np.array([0.0, 0.0, 2000.0])  # every camera of a test rig looks at it (mm)
SIZES = ((1920, 1080), (1280, 1024), (4096, 3072), (640, 480))


#: Realistic wide lenses (core/lens.py): focal length / image width, parameters, their spread.
WIDE_LENSES = {
    "kannala_brandt": (0.26, [0.03, -0.01, 0.004, -0.0008], [0.005, 0.003, 0.001, 0.0002]),
    "mei": (0.55, [1.0, -0.2, 0.05, 1e-3, -1e-3], [0.1, 0.03, 0.01, 5e-4, 5e-4]),
    "double_sphere": (0.3, [-0.2, 0.6], [0.05, 0.03]),
}
#: How far off its axis a test looks through each lens: a pinhole's image, cv2.fisheye's and
#: Kalibr's pinhole-equidistant up to 90 degrees (both divide by Z), the omnidirectional lenses
#: beyond it.
MAX_DEG = {"opencv": 25, "kannala_brandt": 85, "mei": 100, "double_sphere": 100}


def random_camera(rng, name, n_dist, position=None, lens="opencv"):
    """Realistic intrinsics and distortion with ``n_dist`` coefficients (or, for a wide
    ``lens``, its parameters); at ``position`` looking at TARGET (None: the identity pose, a
    rig's camera 0)."""
    w, h = SIZES[rng.integers(len(SIZES))]
    f = rng.uniform(0.7, 1.6) * w
    d = np.zeros(8)
    d[:n_dist] = rng.normal(0, [0.1, 0.05, 0.002, 0.002, 0.01, 0.05, 0.01, 0.005][:n_dist])
    if lens != "opencv":
        scale, params, spread = WIDE_LENSES[lens]
        f, d = scale * w * rng.uniform(0.9, 1.1), np.add(params, rng.normal(0, spread))
    rvec, tvec = np.zeros(3), np.zeros(3)
    if position is not None:
        R = look_at_rotation(position, TARGET, np.array([0.0, -1.0, 0.0]))
        rvec, tvec = matrix_to_rodrigues(R), -R @ position
    return Camera(name, w, h, f * rng.uniform(0.98, 1.02), f, w / 2 + rng.normal(0, 15),
                  h / 2 + rng.normal(0, 15), 0.0, d, rvec, tvec, lens)


def random_rig(rng, n_dists, names=None, lenses=None):
    """Camera 0 at the identity, the others on an arc around it, all looking at TARGET."""
    names = names or [f"cam{i}" for i in range(len(n_dists))]
    lenses = lenses or ["opencv"] * len(n_dists)
    cams = []
    for i, n in enumerate(n_dists):
        position = None if i == 0 else np.array([rng.uniform(-600, 600), rng.uniform(-150, 150),
                                                 rng.uniform(-200, 300)])
        cams.append(random_camera(rng, names[i], n, position, lenses[i]))
    return cams


def view_points(rng, cam, max_deg=None, n=300):
    """World points (mm) the camera sees, up to ``max_deg`` off its axis (MAX_DEG of its lens by
    default), 0.3 to 4 m away: a wide lens's whole field, not only its centre."""
    max_deg = MAX_DEG[cam.model] if max_deg is None else max_deg
    cos_t = rng.uniform(np.cos(np.radians(max_deg)), 1.0, n)
    phi = rng.uniform(0, 2 * np.pi, n)
    sin_t = np.sqrt(1 - cos_t**2)
    P = np.stack([sin_t * np.cos(phi), sin_t * np.sin(phi), cos_t], -1) * rng.uniform(
        300, 4000, (n, 1))
    P = P[cam.sees(P)]
    return (P - cam.tvec) @ cam.R  # cam_from_world inverted: R^T (P - t)


def rig_points(rng, cams, max_deg, n=300):
    """World points (mm) every camera of a rig sees within ``max_deg`` of its axis."""
    out = np.empty((0, 3))
    while len(out) < n:
        X = view_points(rng, cams[0], max_deg, 4 * n)
        for cam in cams[1:]:
            P = cam.world_to_cam(X)
            X = X[cam.sees(P) & (P[:, 2] > np.cos(np.radians(max_deg)) *
                                 np.linalg.norm(P, axis=1))]
        out = np.concatenate([out, X])
    return out[:n]


def random_points(rng, n=300):
    """World points around TARGET, in front of every camera of a test rig (mm)."""
    return TARGET + rng.uniform(-400, 400, (n, 3))


def max_dpx(uv_a, uv_b) -> float:
    return float(np.abs(np.asarray(uv_a) - np.asarray(uv_b)).max())


def cv2_project(X, K, dist, rvec, tvec):
    uv, _ = cv2.projectPoints(np.asarray(X, dtype=np.float64).reshape(-1, 1, 3),
                              np.asarray(rvec, dtype=np.float64), np.asarray(tvec, np.float64),
                              np.asarray(K, dtype=np.float64), np.asarray(dist, np.float64))
    return uv.reshape(-1, 2)


def opencv_projection(X, K, D, lens, rvec, tvec):
    """X (N, 3) projected by OpenCV's function for the lens model (core/lens.py): cv2.projectPoints,
    cv2.fisheye.projectPoints (skew as its alpha = K[0][1] / fx: it reads no K[0][1]) or
    cv2.omnidir.projectPoints (D = xi then its k1 k2 p1 p2); None for the double sphere lens,
    which OpenCV has not."""
    X = np.asarray(X, dtype=np.float64).reshape(1, -1, 3)
    K, D = np.asarray(K, dtype=np.float64), np.asarray(D, dtype=np.float64).reshape(-1)
    rvec, tvec = (np.asarray(v, dtype=np.float64).reshape(3, 1) for v in (rvec, tvec))
    if lens == "opencv":
        return cv2_project(X, K, D, rvec, tvec)
    if lens == "kannala_brandt":
        return cv2.fisheye.projectPoints(X, rvec, tvec, K, D, alpha=K[0, 1] / K[0, 0]
                                         )[0].reshape(-1, 2)
    if lens == "mei":
        return cv2.omnidir.projectPoints(X, rvec, tvec, K, float(D[0]), D[1:])[0].reshape(-1, 2)
    return None


def node_projection(node, X, rvec, tvec, suffix="", keys=("camera_matrix",
                                                          "distortion_coefficients")):
    """X projected by OpenCV through one camera of a cv2.FileStorage file (its matrix, its
    coefficients, the lens its ``lens_model`` names, opencv without one)."""
    lens = node.getNode(f"lens_model{suffix}").string() or "opencv"
    return opencv_projection(X, node.getNode(keys[0]).mat(), node.getNode(keys[1]).mat(), lens,
                             rvec, tvec)


def assert_same_rig(back, cams, X):
    assert [c.name for c in back] == [c.name for c in cams]
    for a, b in zip(cams, back):
        assert b.size == a.size and b.model == a.model
        assert max_dpx(a.project(X), b.project(X)) < TOL_PX


# ----------------------------------------------------------------------------------------------
# OpenCV YAML
# ----------------------------------------------------------------------------------------------

def test_opencv_camera_file_is_exact_and_projects_in_opencv(tmp_path):
    rng = np.random.default_rng(1)
    cam = random_camera(rng, "solo", 8, np.array([100.0, -50.0, 30.0]))
    path = opencv_yaml.write_camera(cam, tmp_path / "solo.yaml")
    back = opencv_yaml.read_camera(path)
    assert np.array_equal(back.K, cam.K) and np.array_equal(back.dist, cam.dist)
    assert np.array_equal(back.rvec, cam.rvec) and np.array_equal(back.tvec, cam.tvec)
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    X = random_points(rng)
    uv = cv2_project(X, fs.getNode("camera_matrix").mat(),
                     fs.getNode("distortion_coefficients").mat(),
                     fs.getNode("rvec_cam_from_world").mat(),
                     fs.getNode("tvec_cam_from_world").mat())
    assert fs.getNode("image_width").real() == cam.width
    assert max_dpx(uv, cam.project(X)) < TOL_PX


@pytest.mark.parametrize("lens", ["opencv", "kannala_brandt"])
def test_opencv_stereo_file_matches_opencv_and_rectifies(tmp_path, lens):
    """A pinhole pair rectified by cv2.stereoRectify; a fisheye pair (cv2.fisheye.stereoCalibrate's
    layout, D1 and D2 of 4 coefficients) by cv2.fisheye.stereoRectify, over 70 degrees."""
    rng = np.random.default_rng(2)
    if lens == "opencv":
        cams = random_rig(rng, [5, 8], ["left", "right"])
        X = random_points(rng)
    else:
        cams = random_rig(rng, [4, 4], ["left", "right"], [lens, lens])
        X = rig_points(rng, cams, 70)
    path = opencv_yaml.write_stereo(cams, tmp_path / "stereo.yaml")
    assert_same_rig(opencv_yaml.read(path), cams, X)
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    m = {k: fs.getNode(k).mat() for k in ("M1", "D1", "M2", "D2", "R", "T", "E", "F", "R1", "R2",
                                          "P1", "P2", "Q")}
    assert [fs.getNode(f"lens_model{i}").string() or "opencv" for i in (1, 2)] == [lens] * 2
    assert max_dpx(node_projection(fs, X, np.zeros(3), np.zeros(3), "1", ("M1", "D1")),
                   cams[0].project(X)) < TOL_PX
    assert max_dpx(node_projection(fs, X, cv2.Rodrigues(m["R"])[0], m["T"], "2", ("M2", "D2")),
                   cams[1].project(X)) < TOL_PX
    # The epipolar geometry and the rectification hold for the cameras' own (exactly
    # undistorted) rays: x2^T E x1 = 0, u2^T F u1 = 0, and equal rows once rectified.
    rays = [np.c_[c.unproject(c.project(X)), np.ones(len(X))] for c in cams]
    assert np.abs(np.einsum("ni,ij,nj->n", rays[1], m["E"], rays[0])).max() < 1e-9
    pix = [r @ c.K.T for r, c in zip(rays, cams)]
    assert np.abs(np.einsum("ni,ij,nj->n", pix[1], m["F"], pix[0])).max() < 1e-9
    rect = [(r @ Rr.T) @ P[:, :3].T for r, Rr, P in zip(rays, (m["R1"], m["R2"]),
                                                         (m["P1"], m["P2"]))]
    # Rows agree for a horizontal baseline, columns for a vertical one (P2's Tx or Ty); compared
    # as the angle atan2(v, 1) of the row v, which a fisheye's rays, nearly parallel to the
    # rectified image plane, leave well-conditioned where v itself loses digits.
    across = 0 if abs(m["P2"][1, 3]) > abs(m["P2"][0, 3]) else 1
    v = [np.arctan2(r[:, across], r[:, 2]) for r in rect]
    assert np.abs(v[0] - v[1]).max() < 1e-12


def test_opencv_multicam_file_matches_opencv(tmp_path):
    rng = np.random.default_rng(3)
    cams = random_rig(rng, [8, 5, 8])
    path = opencv_yaml.write_multicam(cams, tmp_path / "cameras.yaml")
    X = random_points(rng)
    assert_same_rig(opencv_yaml.read(path), cams, X)
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    assert fs.getNode("camera_count").real() == 3
    for i, cam in enumerate(cams):
        node = fs.getNode(f"camera_{i}")
        uv = cv2_project(X, node.getNode("camera_matrix").mat(),
                         node.getNode("distortion_coefficients").mat(),
                         cv2.Rodrigues(node.getNode("R").mat())[0], node.getNode("T").mat())
        assert node.getNode("camera_name").string() == cam.name
        assert max_dpx(uv, cam.project(X)) < TOL_PX


def test_opencv_files_carry_every_lens_for_cv2_fisheye_and_omnidir(tmp_path):
    """The one-camera and multi-camera files name a wide lens by lens_model: read back by the
    module, and by cv2.FileStorage + cv2.fisheye / cv2.omnidir's projectPoints with their skew
    (the double sphere lens, which OpenCV has not, by the module only)."""
    rng = np.random.default_rng(17)
    cams = random_rig(rng, [4, 4, 4, 5], ["fisheye", "omni", "sphere", "pinhole"],
                      ["kannala_brandt", "mei", "double_sphere", "opencv"])
    cams[0], cams[1] = cams[0].with_params(skew=0.4), cams[1].with_params(skew=-0.3)
    multicam = cv2.FileStorage(str(opencv_yaml.write_multicam(cams, tmp_path / "cameras.yaml")),
                               cv2.FILE_STORAGE_READ)
    back = opencv_yaml.read(tmp_path / "cameras.yaml")
    for i, cam in enumerate(cams):
        X = view_points(rng, cam)
        assert_same_rig(back[i:i + 1], [cam], X)
        one = opencv_yaml.write_camera(cam, tmp_path / f"{cam.name}.yaml")
        assert_same_rig(opencv_yaml.read(one), [cam], X)
        fs = cv2.FileStorage(str(one), cv2.FILE_STORAGE_READ)
        node = multicam.getNode(f"camera_{i}")
        for uv in (node_projection(fs, X, fs.getNode("rvec_cam_from_world").mat(),
                                   fs.getNode("tvec_cam_from_world").mat()),
                   node_projection(node, X, cv2.Rodrigues(node.getNode("R").mat())[0],
                                   node.getNode("T").mat())):
            assert (uv is None) == (cam.model == "double_sphere")
            if uv is not None:
                assert max_dpx(uv, cam.project(X)) < TOL_PX
    # export's choice: a pair OpenCV does not rectify goes to the multi-camera file.
    assert [f.name for f in formats.export(cams[1:3], tmp_path / "pair", "opencv",
                                           rebase=True)] == [opencv_yaml.MULTICAM_FILE]
    assert [f.name for f in formats.export(random_rig(rng, [4, 4], None, ["kannala_brandt"] * 2),
                                           tmp_path / "fisheye", "opencv")] == \
        [opencv_yaml.STEREO_FILE]


def test_opencv_stereo_file_refuses_a_pair_opencv_does_not_rectify(tmp_path):
    rng = np.random.default_rng(20)
    for lenses, match in ((["mei", "mei"], ("stereo file: camera 'cam0': a mei lens; the format "
                                            "carries opencv and kannala_brandt lenses only")),
                          (["opencv", "kannala_brandt"],
                           (r"cameras 'cam0' \(opencv lens\) and 'cam1' \(kannala_brandt lens\): "
                            r"OpenCV rectifies a pair of one lens model"))):
        with pytest.raises(ValueError, match=match):
            opencv_yaml.write_stereo(random_rig(rng, [4, 4], None, lenses), tmp_path / "s.yaml")


def test_files_without_a_world_frame_refuse_or_rebase(tmp_path):
    rng = np.random.default_rng(4)
    cams = random_rig(rng, [4, 4, 4])
    # Move the whole rig: camera 0 is no longer the world's origin.
    R0, t0 = rodrigues_to_matrix([0.2, -0.1, 0.05]), np.array([30.0, 40.0, -500.0])
    moved = [c.with_params(rvec=matrix_to_rodrigues(c.R @ R0), tvec=c.R @ t0 + c.tvec)
             for c in cams]
    for write, n in ((opencv_yaml.write_stereo, 2), (opencv_yaml.write_multicam, 3)):
        with pytest.raises(ValueError, match="cam0.*rebase=True"):
            write(moved[:n], tmp_path / "r.yaml")
        back = opencv_yaml.read(write(moved[:n], tmp_path / "r.yaml", rebase=True))
        assert_same_rig(back, cams[:n], random_points(rng))
    with pytest.raises(ValueError, match="rebase=True"):
        kalibr.write(moved, tmp_path)
    assert_same_rig(kalibr.read(kalibr.write(moved, tmp_path, rebase=True)[0]), cams,
                    random_points(rng))


# ----------------------------------------------------------------------------------------------
# COLMAP
# ----------------------------------------------------------------------------------------------

def test_colmap_model_matches_pycolmap(tmp_path):
    pycolmap = pytest.importorskip("pycolmap")
    rng = np.random.default_rng(5)
    cams = random_rig(rng, [4, 8, 5], ["left", "right", "top"])
    colmap.write(cams, tmp_path)
    X = random_points(rng)
    assert_same_rig(colmap.read(tmp_path), cams, X)
    rec = pycolmap.Reconstruction(str(tmp_path))
    assert [rec.cameras[i].model.name for i in (1, 2, 3)] == ["OPENCV", "FULL_OPENCV",
                                                                "FULL_OPENCV"]
    for image in rec.images.values():
        cam = cams[image.camera_id - 1]
        assert image.name == cam.name
        pose = image.cam_from_world()
        Xc = X @ np.asarray(pose.rotation.matrix()).T + np.asarray(pose.translation)
        uv = np.asarray(rec.cameras[image.camera_id].img_from_cam(Xc)) - colmap.PIXEL_SHIFT
        assert max_dpx(uv, cam.project(X)) < TOL_PX
    assert_same_rig(colmap.from_reconstruction(rec), cams, X)
    # A model as COLMAP itself writes it (with rigs.txt and frames.txt) reads back the same.
    (tmp_path / "by_colmap").mkdir()
    rec.write_text(str(tmp_path / "by_colmap"))
    assert_same_rig(colmap.read(tmp_path / "by_colmap"), cams, X)


def test_colmap_opencv_fisheye_is_the_kannala_brandt_lens_for_pycolmap(tmp_path):
    pycolmap = pytest.importorskip("pycolmap")
    rng = np.random.default_rng(6)
    cams = random_rig(rng, [4, 4], ["pinhole", "fisheye"])
    cams[1] = cams[1].with_params(model="kannala_brandt", dist=[0.03, -0.01, 0.004, -0.0008],
                                  fx=0.5 * cams[1].fx, fy=0.5 * cams[1].fy)
    colmap.write(cams, tmp_path)
    X = random_points(rng)
    back = colmap.read(tmp_path)
    assert back[1].model == "kannala_brandt"
    assert_same_rig(back, cams, X)
    rec = pycolmap.Reconstruction(str(tmp_path))
    assert rec.cameras[2].model.name == "OPENCV_FISHEYE"
    image = next(i for i in rec.images.values() if i.camera_id == 2)
    pose = image.cam_from_world()
    Xc = X @ np.asarray(pose.rotation.matrix()).T + np.asarray(pose.translation)
    uv = np.asarray(rec.cameras[2].img_from_cam(Xc)) - colmap.PIXEL_SHIFT
    assert max_dpx(uv, cams[1].project(X)) < TOL_PX


def test_colmap_reads_the_models_it_holds_exactly(tmp_path):
    (tmp_path / "cameras.txt").write_text("1 SIMPLE_RADIAL 640 480 500 320.5 240.5 0.1\n"
                                          "2 PINHOLE 640 480 500 510 300.5 200.5\n")
    (tmp_path / "images.txt").write_text("# comment\n1 1 0 0 0 0 0 0 1 a\n\n"
                                         "2 0 1 0 0 1 2 3 2 b\n1.0 2.0 -1\n")
    a, b = colmap.read(tmp_path / "cameras.txt")
    assert (a.fx, a.fy, a.cx, a.cy, a.dist[0]) == (500, 500, 320, 240, 0.1)
    assert (b.fx, b.fy, b.cx, b.cy) == (500, 510, 300, 200) and not np.any(b.dist)
    assert np.allclose(b.R, np.diag([1.0, -1.0, -1.0])) and np.array_equal(b.tvec, [1, 2, 3])


# ----------------------------------------------------------------------------------------------
# Kalibr
# ----------------------------------------------------------------------------------------------

def test_kalibr_camchain_matches_opencv_projection(tmp_path):
    rng = np.random.default_rng(6)
    cams = random_rig(rng, [4, 4, 4], ["cam_a", "cam_b", "cam_c"])
    (path,) = kalibr.write(cams, tmp_path)
    X = random_points(rng)
    assert_same_rig(kalibr.read(path), cams, X)
    chain = yaml.safe_load(path.read_text())
    assert list(chain) == ["cam0", "cam1", "cam2"]
    T = np.eye(4)  # cam_i_from_cam0, in metres, composed down the chain as Kalibr does
    for i, cam in enumerate(cams):
        entry = chain[f"cam{i}"]
        # The checks of Kalibr's ConfigReader.CameraParameters.
        assert entry["camera_model"] == "pinhole" and entry["distortion_model"] == "radtan"
        assert all(isinstance(v, float) for v in entry["intrinsics"])
        assert all(isinstance(v, int) for v in entry["resolution"])
        assert len(entry["distortion_coeffs"]) == 4 and isinstance(entry["rostopic"], str)
        if i:
            T = np.array(entry["T_cn_cnm1"]) @ T
        fu, fv, pu, pv = entry["intrinsics"]
        uv = cv2_project(X / 1000.0, [[fu, 0, pu], [0, fv, pv], [0, 0, 1]],
                         entry["distortion_coeffs"], cv2.Rodrigues(T[:3, :3])[0], T[:3, 3])
        assert max_dpx(uv, cam.project(X)) < TOL_PX


def kalibr_project(entry, P):
    """Camera-frame points P (N, 3, metres) -> pixels, as Kalibr computes them: the intrinsics in
    the order ConfigReader.py's AslamCamera reads them, the formulas of euclideanToKeypoint in
    aslam_cv/aslam_cameras/include/aslam/cameras/implementation/PinholeProjection.hpp,
    OmniProjection.hpp and DoubleSphereProjection.hpp, and of distort in
    RadialTangentialDistortion.hpp and EquidistantDistortion.hpp (ethz-asl/kalibr)."""
    model, p = entry["camera_model"], entry["intrinsics"]
    x, y, z = np.asarray(P, dtype=np.float64).T
    if model == "pinhole":
        fu, fv, cu, cv = p
        mx, my = x / z, y / z
    elif model == "omni":
        xi, fu, fv, cu, cv = p
        rz = 1.0 / (z + xi * np.sqrt(x * x + y * y + z * z))
        mx, my = x * rz, y * rz
    elif model == "ds":
        xi, alpha, fu, fv, cu, cv = p
        k = xi * np.sqrt(x * x + y * y + z * z) + z
        norm = alpha * np.sqrt(x * x + y * y + k * k) + (1 - alpha) * k
        mx, my = x / norm, y / norm
    else:
        raise AssertionError(f"no Kalibr formula for camera_model {model!r} here")
    if entry["distortion_model"] == "radtan":
        k1, k2, p1, p2 = entry["distortion_coeffs"]
        mx2, my2, mxy = mx * mx, my * my, mx * my
        rho2 = mx2 + my2
        rad = k1 * rho2 + k2 * rho2 * rho2
        mx, my = (mx + mx * rad + 2 * p1 * mxy + p2 * (rho2 + 2 * mx2),
                  my + my * rad + 2 * p2 * mxy + p1 * (rho2 + 2 * my2))
    elif entry["distortion_model"] == "equidistant":
        k1, k2, k3, k4 = entry["distortion_coeffs"]
        r = np.sqrt(mx * mx + my * my)
        theta = np.arctan(r)
        t2 = theta * theta
        thetad = theta * (1 + k1 * t2 + k2 * t2**2 + k3 * t2**3 + k4 * t2**4)
        scaling = np.where(r > 1e-8, thetad / np.where(r > 1e-8, r, 1.0), 1.0)
        mx, my = mx * scaling, my * scaling
    return np.stack([fu * mx + cu, fv * my + cv], -1)


#: Each lens's Kalibr model and the sizes ConfigReader.py checks (checkIntrinsics,
#: checkDistortion): camera_model, distortion_model, len(intrinsics), len(distortion_coeffs).
KALIBR_LAYOUTS = {"opencv": ("pinhole", "radtan", 4, 4),
                  "kannala_brandt": ("pinhole", "equidistant", 4, 4),
                  "mei": ("omni", "radtan", 5, 4), "double_sphere": ("ds", "none", 6, 0)}


def test_kalibr_camchain_carries_each_lens_as_kalibr_projects_it(tmp_path):
    """Each lens written as its Kalibr model (equidistant up to 85 degrees, omni and ds beyond
    90), read back here, and projected down the chain by Kalibr's own formulas."""
    rng = np.random.default_rng(18)
    lenses = list(KALIBR_LAYOUTS)[::-1]
    cams = random_rig(rng, [4] * 4, ["sphere", "omni", "fisheye", "pinhole"], lenses)
    (path,) = kalibr.write(cams, tmp_path)
    back = kalibr.read(path)
    chain = yaml.safe_load(path.read_text())
    T = np.eye(4)  # cam_i_from_cam0 (camera 0 is the world), metres, composed as Kalibr does
    for i, cam in enumerate(cams):
        entry = chain[f"cam{i}"]
        if i:
            T = np.array(entry["T_cn_cnm1"]) @ T
        model, dist_model, n_intrinsics, n_coeffs = KALIBR_LAYOUTS[cam.model]
        assert (entry["camera_model"], entry["distortion_model"]) == (model, dist_model)
        assert len(entry["intrinsics"]) == n_intrinsics
        assert len(entry["distortion_coeffs"]) == n_coeffs
        assert all(isinstance(v, float) for v in entry["intrinsics"] + entry["distortion_coeffs"])
        X = view_points(rng, cam)
        assert_same_rig(back[i:i + 1], [cam], X)
        P = (X / 1000.0) @ T[:3, :3].T + T[:3, 3]
        assert max_dpx(kalibr_project(entry, P), cam.project(X)) < TOL_PX
    # Kalibr's omni-none (its Omni camera, no distortion) reads as Mei's lens without it.
    chain["cam1"].update(distortion_model="none", distortion_coeffs=[])
    (tmp_path / "none").mkdir()
    (tmp_path / "none" / kalibr.FILE).write_text(yaml.safe_dump(chain))
    omni = kalibr.read(tmp_path / "none")[1]
    assert omni.model == "mei" and omni.dist[0] == cams[1].dist[0] and not omni.dist[1:].any()


# ----------------------------------------------------------------------------------------------
# EasyMocap
# ----------------------------------------------------------------------------------------------

def test_easymocap_files_read_as_easymocap_reads_them(tmp_path):
    rng = np.random.default_rng(7)
    cams = random_rig(rng, [5, 4, 5], ["01", "02", "side-3"])
    intri_path, extri_path = easymocap.write(cams, tmp_path)
    X = random_points(rng)
    assert_same_rig(easymocap.read(tmp_path), cams, X)
    # EasyMocap's read_camera: names, K_, dist_, H_, W_ from intri; R_ (Rodrigues), T_ (m).
    intri = cv2.FileStorage(str(intri_path), cv2.FILE_STORAGE_READ)
    extri = cv2.FileStorage(str(extri_path), cv2.FILE_STORAGE_READ)
    node = intri.getNode("names")
    names = [node.at(i).string() or str(int(node.at(i).real())) for i in range(node.size())]
    assert names == [c.name for c in cams]
    for name, cam in zip(names, cams):
        dist = intri.getNode(f"dist_{name}").mat()
        assert dist.shape == (1, 5)  # what EasyMocap's write_intri accepts
        R = cv2.Rodrigues(extri.getNode(f"R_{name}").mat())[0]
        assert np.abs(R - extri.getNode(f"Rot_{name}").mat()).max() < 1e-15
        uv = cv2_project(X / 1000.0, intri.getNode(f"K_{name}").mat(), dist,
                         extri.getNode(f"R_{name}").mat(), extri.getNode(f"T_{name}").mat())
        assert int(intri.getNode(f"W_{name}").real()) == cam.width
        assert max_dpx(uv, cam.project(X)) < TOL_PX


# ----------------------------------------------------------------------------------------------
# anipose
# ----------------------------------------------------------------------------------------------

def test_anipose_file_matches_aniposelib(tmp_path):
    cameras = pytest.importorskip("aniposelib.cameras")
    rng = np.random.default_rng(8)
    cams = random_rig(rng, [5, 8, 8], ["A", "B", "C"])
    (path,) = anipose.write(cams, tmp_path)
    X = random_points(rng)
    assert_same_rig(anipose.read(path), cams, X)
    group = cameras.CameraGroup.load(str(path))
    assert group.metadata["length_unit"] == "mm"
    assert [len(c.get_distortions()) for c in group.cameras] == [5, 8, 8]
    for a, cam in zip(group.cameras, cams):
        assert a.get_name() == cam.name and tuple(a.get_size()) == cam.size
        assert max_dpx(a.project(X).reshape(-1, 2), cam.project(X)) < TOL_PX


def test_anipose_fisheye_tables_are_aniposelibs_fisheye_cameras(tmp_path):
    """Kannala-Brandt lenses written as fisheye = true tables: aniposelib loads them as its
    FisheyeCamera (cv2.fisheye) and projects them as the suite does over 75 degrees; its own
    dump reads back here as the same rig."""
    cameras = pytest.importorskip("aniposelib.cameras")
    rng = np.random.default_rng(19)
    cams = random_rig(rng, [4, 4, 5], ["A", "B", "C"], ["kannala_brandt"] * 2 + ["opencv"])
    (path,) = anipose.write(cams, tmp_path)
    X = rig_points(rng, cams[:2], 75)
    assert_same_rig(anipose.read(path)[:2], cams[:2], X)
    group = cameras.CameraGroup.load(str(path))
    assert [type(c).__name__ for c in group.cameras] == ["FisheyeCamera", "FisheyeCamera",
                                                         "Camera"]
    for a, cam in zip(group.cameras[:2], cams):
        assert len(a.get_distortions()) == 4
        assert max_dpx(a.project(X).reshape(-1, 2), cam.project(X)) < TOL_PX
    group.dump(str(tmp_path / "dumped.toml"))
    assert_same_rig(anipose.read(tmp_path / "dumped.toml")[:2], cams[:2], X)


def test_anipose_keeps_the_order_of_more_than_ten_cameras(tmp_path):
    cameras = pytest.importorskip("aniposelib.cameras")
    rng = np.random.default_rng(9)
    cams = random_rig(rng, [4] * 12)
    (path,) = anipose.write(cams, tmp_path)
    names = [c.name for c in cams]
    assert [c.get_name() for c in cameras.CameraGroup.load(str(path)).cameras] == names
    assert [c.name for c in anipose.read(path)] == names


# ----------------------------------------------------------------------------------------------
# caliscope
# ----------------------------------------------------------------------------------------------

def caliscope_projections(camera, X):
    """X (mm) projected as caliscope does: cv2.projectPoints with its matrix, distortions and
    [R | t] (cam_from_world, metres)."""
    return cv2_project(X / 1000.0, camera.matrix, camera.distortions,
                       cv2.Rodrigues(camera.rotation)[0], camera.translation)


def test_caliscope_file_matches_caliscope(tmp_path):
    """Written here, read by caliscope's CameraArray.from_toml; written by its to_toml, read
    here: the same projections to 1e-9 px both ways (cameras named cam_<id>, in the rig's order)."""
    camera_array = pytest.importorskip("caliscope.cameras.camera_array")
    rng = np.random.default_rng(15)
    cams = random_rig(rng, [5, 8, 5], ["cam_0", "cam_1", "cam_2"])
    (path,) = caliscope.write(cams, tmp_path / "ours")
    X = random_points(rng)
    assert_same_rig(caliscope.read(path), cams, X)
    theirs = camera_array.CameraArray.from_toml(path)
    assert sorted(theirs.cameras) == [0, 1, 2]
    for i, cam in enumerate(cams):
        c = theirs.cameras[i]
        assert tuple(c.size) == cam.size and len(c.distortions) == (8 if i == 1 else 5)
        assert max_dpx(caliscope_projections(c, X), cam.project(X)) < TOL_PX
    theirs.to_toml(tmp_path / "theirs" / caliscope.FILE)
    assert_same_rig(formats.load(tmp_path / "theirs"), cams, X)


def test_caliscope_fisheye_cameras_project_in_caliscope(tmp_path):
    """Kannala-Brandt lenses written as fisheye = true: caliscope's CameraArray.from_toml keeps
    the flag and its own project_points (cv2.fisheye) projects them as the suite does over 75
    degrees; its to_toml reads back here as the same rig."""
    camera_array = pytest.importorskip("caliscope.cameras.camera_array")
    reprojection = pytest.importorskip("caliscope.core.reprojection")
    rng = np.random.default_rng(21)
    cams = random_rig(rng, [4, 4], ["cam_0", "cam_1"], ["kannala_brandt"] * 2)
    (path,) = caliscope.write(cams, tmp_path / "ours")
    X = rig_points(rng, cams, 75)
    assert_same_rig(caliscope.read(path), cams, X)
    theirs = camera_array.CameraArray.from_toml(path)
    for i, cam in enumerate(cams):
        c = theirs.cameras[i]
        assert c.fisheye is True and len(c.distortions) == 4
        uv = reprojection.project_points(X / 1000.0, cv2.Rodrigues(c.rotation)[0], c.translation,
                                         c.matrix, c.distortions, c.fisheye)
        assert max_dpx(uv, cam.project(X)) < TOL_PX
    theirs.to_toml(tmp_path / "theirs" / caliscope.FILE)
    assert_same_rig(formats.load(tmp_path / "theirs"), cams, X)


def test_caliscope_older_sessions_and_intrinsics_only(tmp_path):
    """An older session's config.toml ([cam_<id>], 3x3 rotation) reads as the same rig; an
    array before its extrinsics are calibrated reads as intrinsics at the identity; one where
    only some cameras have a pose, or a camera whose images were turned, is refused."""
    rng = np.random.default_rng(16)
    cams = random_rig(rng, [5, 5], ["cam_0", "cam_1"])
    lines = []
    for i, cam in enumerate(cams):
        lines += [f"[cam_{i}]", f"cam_id = {i}", f"size = {list(cam.size)}",
                  f"matrix = {cam.K.tolist()}", f"distortions = {cam.dist[:5].tolist()}",
                  f"rotation = {cam.R.tolist()}", f"translation = {(cam.tvec / 1e3).tolist()}",
                  ""]
    (tmp_path / "config.toml").write_text("\n".join(lines))
    assert formats.guess_format(tmp_path / "config.toml") == "caliscope"
    assert_same_rig(formats.load(tmp_path), cams, random_points(rng))
    unposed = "\n".join(ln for ln in lines if not ln.startswith(("rotation", "translation")))
    (tmp_path / "config.toml").write_text(unposed)
    back = formats.load(tmp_path)
    assert [c.fx for c in back] == [c.fx for c in cams]
    assert all(not c.rvec.any() and not c.tvec.any() for c in back)
    (tmp_path / "config.toml").write_text("\n".join(lines[:8]) + "\n" + unposed.split("\n\n")[1])
    with pytest.raises(ValueError, match="cam_1 have no rotation and translation"):
        formats.load(tmp_path)
    (tmp_path / "config.toml").write_text("\n".join(lines).replace("cam_id = 1", "cam_id = 1\n"
                                                                     "rotation_count = 1"))
    with pytest.raises(ValueError, match=r"\[cam_1\]: rotation_count 1: its images were turned"):
        formats.load(tmp_path)


# ----------------------------------------------------------------------------------------------
# mrcal
# ----------------------------------------------------------------------------------------------

def mrcal_python() -> str:
    """A Python that imports mrcal (it has no wheel for this Python): SYNTHCAL_MRCAL_PYTHON, or
    the environment .venv/mrcal (docs/formats.md says how to make it)."""
    from stereo_bench.tools.mrcal import python

    exe = str(python())
    if not Path(exe).is_file() or subprocess.run([exe, "-c", "import mrcal"],
                                                 capture_output=True).returncode:
        pytest.skip(f"no Python with mrcal at {exe} (set SYNTHCAL_MRCAL_PYTHON)")
    return exe


MRCAL_PROJECT = """
import sys, numpy as np, mrcal
X = np.load(sys.argv[1])
models = [mrcal.cameramodel(f) for f in sys.argv[3:]]
np.save(sys.argv[2], np.stack([mrcal.project(mrcal.transform_point_rt(m.rt_cam_ref(), X),
                                             *m.intrinsics()) for m in models]))
"""


def mrcal_projections(exe, files, X, tmp_path) -> np.ndarray:
    np.save(tmp_path / "X.npy", X)
    subprocess.run([exe, "-c", MRCAL_PROJECT, str(tmp_path / "X.npy"), str(tmp_path / "uv.npy"),
                    *map(str, files)], check=True, capture_output=True)
    return np.load(tmp_path / "uv.npy")


def test_mrcal_file_layout_and_lens_models(tmp_path):
    rng = np.random.default_rng(10)
    cams = random_rig(rng, [4, 5, 8], ["left", "mid", "right"])
    files = mrcal.write(cams, tmp_path)
    X = random_points(rng)
    assert_same_rig(mrcal.read(tmp_path), cams, X)
    for f, cam, model in zip(files, cams, ("OPENCV4", "OPENCV5", "OPENCV8")):
        d = ast.literal_eval(f.read_text())
        assert d["lensmodel"] == f"LENSMODEL_{model}" and d["rt_cam_ref"] == d["extrinsics"]
        assert d["imagersize"] == [cam.width, cam.height]
        p = np.array(d["intrinsics"])
        K = [[p[0], 0, p[2]], [0, p[1], p[3]], [0, 0, 1]]
        uv = cv2_project(X, K, p[4:], d["rt_cam_ref"][:3], d["rt_cam_ref"][3:])
        assert max_dpx(uv, cam.project(X)) < TOL_PX


def test_mrcal_reads_the_files_and_kalibr_chain(tmp_path):
    exe = mrcal_python()
    rng = np.random.default_rng(11)
    cams = random_rig(rng, [4, 5, 8])
    X = random_points(rng)
    uv = mrcal_projections(exe, mrcal.write(cams, tmp_path), X, tmp_path)
    for u, cam in zip(uv, cams):
        assert max_dpx(u, cam.project(X)) < TOL_PX
    # mrcal's own Kalibr reader on this module's camchain.yaml.
    cams4 = [c.with_params(dist=c.dist[:4]) for c in cams]
    (chain,) = kalibr.write(cams4, tmp_path)
    out = tmp_path / "from_kalibr"
    out.mkdir()
    subprocess.run([exe, str(Path(exe).parent / "mrcal-from-kalibr"), "--outdir", str(out),
                    str(chain)], check=True, capture_output=True)
    files = sorted(out.glob("*.cameramodel"))
    assert len(files) == 3
    uv = mrcal_projections(exe, files, X / 1000.0, tmp_path)  # Kalibr's metres
    # mrcal-from-kalibr writes its models with 10 significant digits (measured: up to 6e-7 px
    # over 20 rigs), so this leg is held to 1e-5 px.
    for u, cam in zip(uv, cams4):
        assert max_dpx(u, cam.project(X)) < 1e-5


def test_mrcal_from_kalibr_converts_no_wide_lens(tmp_path):
    """mrcal's Kalibr converter takes pinhole-radtan and pinhole-none only, so the chain's wide
    lenses are checked against Kalibr's own formulas (kalibr_project) instead."""
    exe = mrcal_python()
    rng = np.random.default_rng(22)
    for lens in ("kannala_brandt", "mei", "double_sphere"):
        (chain,) = kalibr.write([random_camera(rng, "c", 4, lens=lens)], tmp_path / lens)
        run = subprocess.run([exe, str(Path(exe).parent / "mrcal-from-kalibr"), "--outdir",
                              str(tmp_path / lens), str(chain)], capture_output=True, text=True,
                             check=False)  # its refusal is the point
        assert run.returncode != 0 and "only support kalibr" in run.stderr
        assert not list((tmp_path / lens).glob("*.cameramodel"))


# ----------------------------------------------------------------------------------------------
# The registry, the refusals, malformed files
# ----------------------------------------------------------------------------------------------

SUBSETS = {"opencv": 8, "colmap": 8, "kalibr": 4, "easymocap": 5, "anipose": 8, "caliscope": 8,
           "mrcal": 8, "multical": 8}


@pytest.mark.parametrize("fmt", list(formats.FORMATS))
def test_export_and_load_guess_every_format(tmp_path, fmt):
    rng = np.random.default_rng(12)
    # caliscope keeps no names: its cameras are cam_<id>.
    cams = random_rig(rng, [SUBSETS[fmt]] * 3,
                      [f"cam_{i}" for i in range(3)] if fmt == "caliscope" else None)
    files = formats.export(cams, tmp_path / fmt, fmt)
    X = random_points(rng)
    assert_same_rig(formats.load(tmp_path / fmt), cams, X)
    # A file alone: mrcal's holds one camera, the others the whole rig.
    assert_same_rig(formats.load(files[0]), cams[:1] if fmt == "mrcal" else cams, X)
    assert formats.guess_format(files[0]) == fmt


def test_load_and_export_name_what_they_cannot_handle(tmp_path):
    with pytest.raises(ValueError, match="format 'matlab'"):
        formats.export([], tmp_path, "matlab")
    (tmp_path / "notes.txt").write_text("x")
    with pytest.raises(ValueError, match="notes.txt: cannot tell the format"):
        formats.load(tmp_path / "notes.txt")
    with pytest.raises(ValueError, match="cannot tell the format of this folder"):
        formats.load(tmp_path)


@pytest.mark.parametrize("fmt, change, match", [
    ("colmap", {"skew": 0.5}, "skew 0.5 is not 0; COLMAP"),
    ("kalibr", {"skew": 0.5}, "skew 0.5 is not 0; Kalibr"),
    ("easymocap", {"skew": 0.5}, "skew 0.5 is not 0; EasyMocap"),
    ("anipose", {"skew": 0.5}, "skew 0.5 is not 0; aniposelib"),
    ("caliscope", {"skew": 0.5}, "skew 0.5 is not 0; caliscope"),
    ("mrcal", {"skew": 0.5}, "skew 0.5 is not 0; mrcal"),
    ("kalibr", {"dist": [0.1, 0.01, 0, 0, 0.003]}, "k3 = 0.003 is not 0; Kalibr's radtan"),
    ("easymocap", {"dist": [0.1, 0.01, 0, 0, 0.003, 0.02]}, "k4 = 0.02 is not 0; EasyMocap"),
    ("colmap", {"name": "left cam"}, "without whitespace"),
    ("easymocap", {"name": "cam.1"}, "letters, digits"),
])
def test_formats_refuse_what_they_cannot_hold(tmp_path, fmt, change, match):
    cams = random_rig(np.random.default_rng(13), [4, 4])
    cams[1] = cams[1].with_params(**change)
    with pytest.raises(ValueError, match=f"camera '{cams[1].name}': .*{match}"):
        formats.export(cams, tmp_path, fmt)


#: The lens models each format carries (the others refused); kalibr and opencv carry all four.
CARRIED = {"colmap": "opencv and kannala_brandt", "easymocap": "opencv",
           "anipose": "opencv and kannala_brandt", "caliscope": "opencv and kannala_brandt",
           "mrcal": "opencv", "multical": "opencv"}


@pytest.mark.parametrize("fmt, lens", [(fmt, lens) for fmt in CARRIED
                                       for lens in ("kannala_brandt", "mei", "double_sphere")
                                       if lens not in CARRIED[fmt]])
def test_formats_refuse_a_lens_they_have_no_model_of(tmp_path, fmt, lens):
    cams = random_rig(np.random.default_rng(23), [4, 4], ["cam_0", "cam_1"], ["opencv", lens])
    expected = (f"{formats.FORMATS[fmt].FORMAT}: camera 'cam_1': a {lens} lens; the format "
                f"carries {CARRIED[fmt]} lenses only")
    with pytest.raises(ValueError, match=f"^{re.escape(expected)}$"):
        formats.export(cams, tmp_path, fmt)
    assert not list(tmp_path.iterdir())  # nothing written


def test_opencv_stereo_refuses_skew_the_single_file_keeps_it(tmp_path):
    cams = random_rig(np.random.default_rng(14), [5, 5])
    cams[0] = cams[0].with_params(skew=0.25)
    with pytest.raises(ValueError, match="skew 0.25 .*stereoRectify"):
        opencv_yaml.write_stereo(cams, tmp_path / "s.yaml")
    assert opencv_yaml.read_camera(opencv_yaml.write_camera(cams[0], tmp_path / "c.yaml")
                                   ).skew == 0.25


MALFORMED = [
    ("colmap", "cameras.txt", "1 OPENCV 640\n", r"cameras.txt:1: expected CAMERA_ID"),
    ("colmap", "cameras.txt", "1 THIN_PRISM_FISHEYE 640 480 1 2 3 4 0 0 0 0 0 0 0 0\n",
     r"cameras.txt:1: camera model THIN_PRISM_FISHEYE is not one of"),
    ("kalibr", "camchain.yaml", "cam0:\n  camera_model: pinhole\n",
     r"camchain.yaml: cam0: missing 'distortion_model'"),
    ("kalibr", "camchain.yaml", ("cam0:\n  camera_model: eucm\n  distortion_model: none\n"
                                 "  intrinsics: [0.6, 1, 2, 3, 4, 5]\n  distortion_coeffs: []\n"
                                 "  resolution: [6, 7]\n"),
     r"camchain.yaml: cam0: camera_model 'eucm' with distortion_model 'none' is not one of"),
    ("kalibr", "camchain.yaml", ("cam0:\n  camera_model: omni\n  distortion_model: radtan\n"
                                 "  intrinsics: [1, 2, 3, 4]\n  distortion_coeffs: [0, 0, 0, 0]\n"
                                 "  resolution: [6, 7]\n"),
     r"cam0: intrinsics \[xi, fu, fv, pu, pv\]: expected shape \(5,\)"),
    ("easymocap", "intri.yml", "%YAML:1.0\n---\nnames: [\"a\"]\n", r"intri.yml: camera 'a': K_a"),
    ("anipose", "calibration.toml", "[cam_0\nname = 1", r"calibration.toml: not TOML"),
    ("anipose", "calibration.toml", "[cam_0]\nname = \"a\"\n", r"\[cam_0\]: missing 'matrix'"),
    ("caliscope", "camera_array.toml", "[cameras.x]\nsize = [1, 1]\n",
     r"camera_array.toml: \[cameras.x\]: expected a camera id"),
    ("caliscope", "camera_array.toml", ("[cameras.0]\nfisheye = true\nsize = [6, 7]\n"
                                        "matrix = [[1, 0, 3], [0, 1, 3], [0, 0, 1]]\n"
                                        "distortions = [0, 0, 0, 0, 0]\n"),
     r"\[cameras.0\]: a fisheye camera with 5 distortions; cv2.fisheye's model has 4"),
    ("anipose", "calibration.toml", "[cam_0]\nfisheye = \"yes\"\n",
     r"\[cam_0\]: fisheye = 'yes'; expected true or false"),
    ("mrcal", "a.cameramodel", "{'lensmodel': 'LENSMODEL_OPENCV4',", r"a.cameramodel: not a "),
    ("mrcal", "b.cameramodel", "{'lensmodel': 'LENSMODEL_SPLINED_STEREOGRAPHIC_order=3', "
     "'intrinsics': [], 'rt_cam_ref': [0, 0, 0, 0, 0, 0], 'imagersize': [1, 1]}",
     r"b.cameramodel: lensmodel"),
    ("opencv", "c.yaml", "%YAML:1.0\n---\ncamera_matrix: [1, 2\n", r"c.yaml: not an OpenCV"),
    ("opencv", "d.yaml", "%YAML:1.0\n---\nimage_width: 3\n", r"d.yaml: expected 'camera_matrix'"),
    # OpenCV raises for an opencv-matrix whose data is not numbers, or not rows x cols of them.
    ("opencv", "e.yaml", "%YAML:1.0\n---\nimage_width: 3\nimage_height: 3\ncamera_matrix: "
     "!!opencv-matrix\n  rows: 3\n  cols: 3\n  dt: d\n  data: [1, 0, 1, 0, 1, 1, 0, 0, []]\n",
     r"e.yaml: camera_matrix: expected an opencv-matrix"),
    ("opencv", "f.yaml", "%YAML:1.0\n---\nimage_width: 3\nimage_height: 3\ncamera_matrix: "
     "!!opencv-matrix\n  rows: 3\n  cols: 3\n  dt: d\n  data: [1, 0, 1, 0, 1, 1, 0, 0]\n",
     r"f.yaml: camera_matrix: expected an opencv-matrix"),
]


@pytest.mark.parametrize("fmt, name, text, match", MALFORMED)
def test_malformed_files_give_errors_naming_them(tmp_path, fmt, name, text, match):
    (tmp_path / name).write_text(text)
    if fmt == "colmap":
        (tmp_path / "images.txt").write_text("1 1 0 0 0 0 0 0 1 a\n\n")
    if fmt == "easymocap":
        (tmp_path / "extri.yml").write_text("%YAML:1.0\n---\nnames: [\"a\"]\n")
    with pytest.raises(ValueError, match=match):
        formats.load(tmp_path / name, fmt)
