"""The next view to shoot: it goes where the calibration is least certain, its predicted effect
is what a real refit with that view gives, and it beats the same board put at the centre."""

import numpy as np
import pytest

from stereo_bench.calibrate import Observations, get_calibrator
from stereo_bench.core.camera import Camera
from stereo_bench.core.poses import matrix_to_rodrigues, rodrigues_to_matrix
from stereo_bench.calibrate.next_view import placed, suggest
from stereo_bench.core.patterns import Checkerboard
from stereo_bench.calibrate.uncertainty import median_board_distance, residual_sigma, worst_sigma

NOISE_PX = 0.2
TRUE = Camera("cam", 640, 480, 600.0, 600.0, 322.0, 238.0, 0.0,
              np.array([-0.25, 0.08, 0.001, -0.0005, 0.0, 0, 0, 0]), np.zeros(3), np.zeros(3))
BOARD = Checkerboard(squares_x=8, squares_y=6, square_mm=25.0).object_points()


def _view(rng, rvec, tvec):
    uv = TRUE.with_params(rvec=rvec, tvec=tvec).project(BOARD)
    return uv + rng.normal(0, NOISE_PX, uv.shape)


def _left_half_capture(seed=0):
    """12 views of a board held only in the left half of the image, tilted every way."""
    rng = np.random.default_rng(seed)
    obj, img = [], []
    while len(img) < 12:
        tilt = rng.normal(0, 0.45, 3)
        tilt[2] = rng.normal(0, 0.2)
        R = rodrigues_to_matrix(tilt)
        t = np.array([rng.uniform(-260, -60), rng.uniform(-120, 120), rng.uniform(550, 800)])
        t -= R @ BOARD.mean(0)
        uv = TRUE.with_params(rvec=matrix_to_rodrigues(R), tvec=t).project(BOARD)
        if (uv.min() < 5) or (uv[:, 0].max() > 300) or (uv[:, 1].max() > 474):
            continue
        obj.append(BOARD)
        img.append(uv + rng.normal(0, NOISE_PX, uv.shape))
    return Observations(obj, img, TRUE.size, list(range(len(img))), "cam")


def test_the_suggestion_goes_where_nothing_was_seen_and_beats_a_centred_board():
    obs = _left_half_capture()
    calibrator = get_calibrator("opencv")
    fit = calibrator.calibrate(obs)
    params = calibrator.model_parameters
    views = suggest(fit.camera, obs, fit.rvecs, fit.tvecs, params, BOARD)
    assert len(views) == 3
    first = views[0]
    # The right half was never seen: the least certain ninth is on the right.
    assert "right" in first["region"] and first["pixel"][0] > 400
    assert first["sigma_after_px"] < first["sigma_px"] / 3
    distance = median_board_distance(obs, fit.rvecs, fit.tvecs)
    # The same board facing the camera at the image's centre does much less there.
    rvec, tvec, uv = placed(fit.camera, BOARD, np.array([319.5, 239.5]), distance, np.eye(3))
    centred = Observations(obs.object_points + [BOARD], obs.image_points + [uv], obs.image_size,
                           obs.view_ids + [99], "cam")
    at_centre = worst_sigma(fit.camera, centred, np.vstack([fit.rvecs, rvec]),
                            np.vstack([fit.tvecs, tvec]), params, np.array([first["pixel"]]),
                            distance,
                            sigma_px=residual_sigma(fit.camera, obs, fit.rvecs, fit.tvecs,
                                                    params))[0]
    assert first["sigma_after_px"] < 0.5 * at_centre
    # Each suggestion counts the ones before it as taken: the second goes elsewhere.
    assert views[1]["region"] != first["region"]
    assert all(len(v["outline_px"]) >= 4 for v in views)


@pytest.mark.parametrize("seed", range(4))
def test_the_predicted_effect_is_what_a_refit_with_the_view_gives(seed):
    """A real refit with the suggested view (detected with noise through the true camera):
    the uncertainty at the target pixel is the predicted one within a factor 1.6 (measured over
    5 captures x 10 refits: 0.76-1.47 times the prediction; the estimate the prediction
    linearizes at extrapolates its distortion where nothing was seen), while the view lowers it
    6-30 times."""
    obs = _left_half_capture(seed)
    calibrator = get_calibrator("opencv")
    fit = calibrator.calibrate(obs)
    params = calibrator.model_parameters
    first = suggest(fit.camera, obs, fit.rvecs, fit.tvecs, params, BOARD)[0]
    rng = np.random.default_rng(5)
    more = Observations(obs.object_points + [BOARD],
                        obs.image_points + [_view(rng, np.array(first["rvec"]),
                                                  np.array(first["tvec"]))],
                        obs.image_size, obs.view_ids + [99], "cam")
    refit = calibrator.calibrate(more)
    actual = worst_sigma(refit.camera, more, refit.rvecs, refit.tvecs, params,
                         np.array([first["pixel"]]),
                         median_board_distance(obs, fit.rvecs, fit.tvecs))[0]
    assert first["sigma_after_px"] / 1.6 < actual < 1.6 * first["sigma_after_px"]
    assert actual < first["sigma_px"] / 4
