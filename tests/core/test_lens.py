"""The wide-angle lens models of core/lens.py: OpenCV's own projections, Jacobians against finite
differences, exact unprojection (beyond 90 degrees where the model sees there), valid regions."""

import cv2
import numpy as np
import pytest

from stereo_bench.core.camera import Camera, project_cam_with_jacobians
from stereo_bench.core.lens import LENS_MODELS

INTR = np.array([500.0, 510.0, 640.0, 480.0, 0.7])
LENSES = {
    "kannala_brandt": [0.02, -0.01, 0.003, -0.0005],
    "mei": [1.1, -0.2, 0.05, 1e-3, -2e-3],
    "double_sphere": [-0.2, 0.6],
}


def _points(n=300, seed=0):
    """Camera-frame points all around the camera (the wide models see beyond 90 degrees)."""
    rng = np.random.default_rng(seed)
    return rng.normal(size=(n, 3)) * [400, 300, 200] + [0, 0, 300]


@pytest.mark.parametrize("model", LENSES)
def test_jacobians_match_finite_differences(model):
    params = np.array(LENSES[model])
    cam = Camera("c", 1280, 960, *INTR, params, model=model)
    P = _points()
    P = P[cam.sees(P)]
    uv, J = project_cam_with_jacobians(P, INTR, params, True, model)
    for i in range(3):
        d = np.zeros(3)
        d[i] = 1e-4
        fd = (project_cam_with_jacobians(P + d, INTR, params, False, model)[0]
              - project_cam_with_jacobians(P - d, INTR, params, False, model)[0]) / 2e-4
        np.testing.assert_allclose(J["point"][:, :, i], fd, rtol=1e-6, atol=1e-7)
    for i in range(len(params)):
        d = np.zeros(len(params))
        d[i] = 1e-7
        fd = (project_cam_with_jacobians(P, INTR, params + d, False, model)[0]
              - project_cam_with_jacobians(P, INTR, params - d, False, model)[0]) / 2e-7
        np.testing.assert_allclose(J["dist"][:, :, i], fd, rtol=1e-6, atol=1e-5)
    for i in range(5):
        d = np.zeros(5)
        d[i] = 1e-6
        fd = (project_cam_with_jacobians(P, INTR + d, params, False, model)[0]
              - project_cam_with_jacobians(P, INTR - d, params, False, model)[0]) / 2e-6
        np.testing.assert_allclose(J["intrinsics"][:, :, i], fd, atol=1e-6)


def test_kannala_brandt_on_the_axis_has_the_limit_jacobian():
    params = np.array(LENSES["kannala_brandt"])
    P = np.array([[0.0, 0.0, 700.0], [1e-9, 0.0, 700.0]])
    _, J = project_cam_with_jacobians(P, INTR, params, True, "kannala_brandt")
    np.testing.assert_allclose(J["point"][0], J["point"][1], rtol=1e-9, atol=1e-11)


def test_kannala_brandt_is_cv2_fisheye():
    params = np.array(LENSES["kannala_brandt"])
    P = _points()
    P = P[P[:, 2] > 0]  # cv2.fisheye's atan(r) stops at 90 degrees
    K = np.array([[INTR[0], INTR[4], INTR[2]], [0, INTR[1], INTR[3]], [0, 0, 1]])
    ref = cv2.fisheye.projectPoints(P[None], np.zeros(3), np.zeros(3), K, params,
                                    alpha=INTR[4] / INTR[0])[0][0]
    cam = Camera.from_K("c", 1280, 960, K, params, model="kannala_brandt")
    assert np.abs(cam.project(P) - ref).max() < 1e-9


def test_mei_is_cv2_omnidir():
    xi, *D = LENSES["mei"]
    P = _points()
    K = np.array([[INTR[0], INTR[4], INTR[2]], [0, INTR[1], INTR[3]], [0, 0, 1]])
    ref = cv2.omnidir.projectPoints(P[None], np.zeros(3), np.zeros(3), K, xi, np.array(D))[0][0]
    cam = Camera.from_K("c", 1280, 960, K, LENSES["mei"], model="mei")
    seen = cam.sees(P)
    assert seen.mean() > 0.9
    assert np.abs(cam.project(P[seen]) - ref[seen]).max() < 1e-9


@pytest.mark.parametrize("model", LENSES)
def test_unprojection_is_exact_beyond_90_degrees(model):
    cam = Camera("c", 1280, 960, *INTR, LENSES[model], model=model)
    P = _points(2000)
    seen = cam.sees(P)
    assert np.any(P[seen, 2] < 0)  # rays behind the camera's plane are among them
    rays = cam.unproject_rays(cam.project(P[seen]))
    np.testing.assert_allclose(rays, P[seen] / np.linalg.norm(P[seen], axis=1, keepdims=True),
                               atol=1e-12)


def test_a_circular_fisheye_has_no_rays_outside_its_image_circle():
    # k1 < 0 turns theta_d back at theta = 1 / sqrt(3 * 0.05) (148 degrees), radius 1.72 f.
    f, k1 = 250.0, -0.05
    cam = Camera("c", 1000, 1000, f, f, 499.5, 499.5, 0, [k1, 0, 0, 0], model="kannala_brandt")
    uv = np.array([[499.5, 499.5], [499.5 + 399, 499.5], [499.5 + 420, 499.5], [0, 0]])
    assert cam.has_ray(uv).tolist() == [True, True, True, False]
    theta = np.arccos(cam.unproject_rays(uv[:3])[:, 2])
    np.testing.assert_allclose(theta * (1 + k1 * theta**2), [0, 399 / f, 420 / f], atol=1e-13)
    assert np.degrees(theta[2]) > 90
    assert cam.max_normalized_radius == np.inf


@pytest.mark.parametrize("model", LENSES)
def test_a_camera_with_a_lens_model_survives_its_json(model, tmp_path):
    cam = Camera("c", 1280, 960, *INTR, LENSES[model], rvec=[0.1, 0.2, 0.3], tvec=[1, 2, 3],
                 model=model)
    cam.save_json(tmp_path / "c.json")
    back = Camera.load_json(tmp_path / "c.json")
    assert back.model == model and back.to_dict() == cam.to_dict()


def test_lens_parameters_are_checked():
    with pytest.raises(ValueError, match="kannala_brandt lens has 4 parameters"):
        Camera("c", 100, 100, 50, 50, 50, 50, 0, [0.1, 0.2], model="kannala_brandt")
    with pytest.raises(ValueError, match="alpha must lie in"):
        Camera("c", 100, 100, 50, 50, 50, 50, 0, [0.1, 1.2], model="double_sphere")
    with pytest.raises(ValueError, match="unknown lens model 'fish'"):
        Camera("c", 100, 100, 50, 50, 50, 50, 0, [], model="fish")
    assert set(LENS_MODELS) == {"opencv", "kannala_brandt", "mei", "double_sphere"}
