"""The imaging model (render/imaging.py), the board as made (board_shape.py) and the environment
presets, each against an independent computation: thin-lens optics, the photon transfer curve,
a box filter for linear motion, a disc filter for uniform defocus, and ground truth corners.
"""

from pathlib import Path

import cv2
import numpy as np
import pytest

from render_scene import BOARD, CENTRE, OBJ, PINHOLE, WIDE, detect
from stereo_bench.core.board_shape import BoardShape
from stereo_bench.core.poses import rodrigues_to_matrix
from stereo_bench.config.bounds import ConfigError
from stereo_bench.config.schema import load_rig, parse_rig
from stereo_bench.config.environments import PRESETS
from stereo_bench.render import AnalyticRenderer, RenderSettings
from stereo_bench.render.imaging import (Light, Motion, Optics, Sensor, blinn_phong, disc_kernel,
                                         camera_vignette, expose, photograph, vignetting_gain,
                                         vignetting_map)
from stereo_bench.render.texels import NORMAL_QUANTILES, noise_draws, time_area_offsets


def frontal(depth=400.0, shift=(0.0, 0.0)):
    """cam_from_board of the board facing the camera, its centre at (shift, depth)."""
    R = np.eye(3)
    return R, np.array([shift[0], shift[1], depth]) - R @ CENTRE


def tilted(seed=3, depth=420.0):
    rng = np.random.default_rng(seed)
    R = rodrigues_to_matrix([rng.uniform(-0.5, 0.5), rng.uniform(-0.5, 0.5), 0.2])
    return R, np.array([10.0, -5.0, depth]) - R @ CENTRE


def project(cam, R, t, points):
    return cam.project_cam(points @ R.T + t)


# --- the board as made ------------------------------------------------------------------------
def test_board_shape_follows_its_definition_and_inverts_on_rays():
    shape = BoardShape.for_pattern(BOARD, scale_error_pct=0.5, aspect_error_pct=-0.3,
                                   warp_mm=(2.0, 1.0))
    P = shape.points(OBJ)
    lo, hi = OBJ[:, :2].min(0), OBJ[:, :2].max(0)
    centre = (lo + hi) / 2
    # Scale about the grid's centre: x by 1.005, y by 1.005 * 0.997.
    assert np.allclose(P[:, 0] - centre[0], 1.005 * (OBJ[:, 0] - centre[0]), atol=1e-12)
    assert np.allclose(P[:, 1] - centre[1], 1.005 * 0.997 * (OBJ[:, 1] - centre[1]), atol=1e-12)
    # mrcal's warp: zero on the grid's edges, the sum of both deflections at its centre (the
    # grid has an even count of corners per side, so its middle is between corners).
    corner = (OBJ[:, 0] == lo[0]) & (OBJ[:, 1] == lo[1])
    assert P[corner, 2] == pytest.approx(0.0, abs=1e-12)
    assert shape.height(centre[None])[0] == pytest.approx(-3.0)
    # Rays through the physical points find their nominal points again.
    R, t = tilted()
    cam_pts = P @ R.T + t
    xy = cam_pts[:, :2] / cam_pts[:, 2:]
    nominal, depth = shape.nominal_on_rays(xy, R, t)
    assert np.abs(nominal - OBJ[:, :2]).max() < 1e-4  # four fixed-point iterations
    assert np.allclose(depth, cam_pts[:, 2], atol=1e-4)
    nominal32, _ = shape.nominal_on_rays(xy.astype(np.float32), R.astype(np.float32),
                                         t.astype(np.float32))
    assert np.abs(nominal32 - OBJ[:, :2]).max() < 2e-3  # float32: what the renderer uses


def test_a_warped_misprinted_board_renders_at_its_physical_corners(rays):
    """Detections on a render of the board as made agree with the projections of its physical
    points as closely as detections on the nominal board agree with its own; the nominal
    points are pixels away."""
    shape = BoardShape.for_pattern(BOARD, scale_error_pct=1.0, aspect_error_pct=0.8,
                                   warp_mm=(4.0, 3.0))
    physical = shape.points(OBJ)
    for cam in (PINHOLE, WIDE):
        R, t = tilted(depth=380.0)
        err = {}
        for name, board, points in (("made", shape, physical), ("nominal", None, OBJ)):
            img = AnalyticRenderer(cam, BOARD, RenderSettings(board=board), rays(cam)).render(R, t)
            truth = project(cam, R, t, points)
            err[name] = np.linalg.norm(detect(img, truth) - truth, axis=1)
        nominal_off = np.linalg.norm(project(cam, R, t, OBJ) - project(cam, R, t, physical), axis=1)
        print(f"{cam.name}: detection vs truth, board as made mean {err['made'].mean():.4f} px "
              f"(max {err['made'].max():.4f}), nominal board {err['nominal'].mean():.4f} px "
              f"(max {err['nominal'].max():.4f}); nominal points off by up to "
              f"{nominal_off.max():.2f} px")
        assert err["made"].mean() < err["nominal"].mean() + 0.01
        assert err["made"].max() < 0.15
        assert nominal_off.max() > 1.0


# --- optics -----------------------------------------------------------------------------------
def test_circle_of_confusion_is_the_thin_lens_blur():
    """Against the lens equation directly: the sensor sits where the focus distance images, a
    point at depth d images at v(d), and the aperture's cone is cut by the sensor."""
    optics = Optics(f_number=2.8, focal_length_mm=8.0, focus_distance_mm=600.0)
    fx = 1200.0  # px; the pixel pitch is 8 / 1200 mm
    depth = np.array([300.0, 500.0, 600.0, 900.0, 5000.0])

    def image_distance(d):
        return 1.0 / (1.0 / 8.0 - 1.0 / d)

    aperture = 8.0 / 2.8
    v_sensor = image_distance(600.0)
    blur_mm = aperture * np.abs(image_distance(depth) - v_sensor) / image_distance(depth)
    # fx is the principal distance (the sensor's, v_sensor) over the pixel pitch.
    expected = blur_mm / (v_sensor / fx)
    assert np.allclose(optics.circle_of_confusion_px(depth, fx), expected, rtol=1e-12)
    assert optics.circle_of_confusion_px(np.array([600.0]), fx)[0] == 0.0
    assert np.all(Optics().circle_of_confusion_px(depth, fx) == 0)  # a pinhole


@pytest.mark.parametrize("radius", [0.0, 0.3, 1.0, 2.5, 6.0])
def test_disc_kernel_is_a_normalized_uniform_disc(radius):
    k = disc_kernel(radius)
    n = k.shape[0] // 2
    assert k.shape[0] == k.shape[1] and k.sum() == pytest.approx(1.0, abs=1e-6)
    assert np.allclose(k, k[::-1]) and np.allclose(k, k.T)  # point-symmetric: edges do not move
    x = np.arange(-n, n + 1)
    var = float((k.sum(0) * x * x).sum())
    # A uniform disc's variance along x is r^2 / 4, plus the pixel box's 1/12 once it is
    # resolved (area-share taps).
    if radius >= 2.5:
        assert var == pytest.approx(radius**2 / 4 + 1 / 12, rel=0.03)


def test_uniform_defocus_is_a_disc_convolution(rays):
    """A fronto-parallel board is at one depth: its defocused render is its sharp render
    convolved with one disc of the thin-lens diameter."""
    optics = Optics(f_number=1.4, focal_length_mm=6.0, focus_distance_mm=250.0)
    R, t = frontal(depth=400.0)
    sharp = AnalyticRenderer(PINHOLE, BOARD, RenderSettings(), rays(PINHOLE)).render(R, t)
    blurred = AnalyticRenderer(PINHOLE, BOARD, RenderSettings(optics=optics),
                               rays(PINHOLE)).render(R, t)
    diameter = optics.circle_of_confusion_px(np.array([400.0]), PINHOLE.fx)[0]
    assert 3.0 < diameter < 8.0
    expected = cv2.filter2D(sharp.astype(np.float32), -1, disc_kernel(diameter / 2),
                            borderType=cv2.BORDER_REPLICATE)
    diff = np.abs(blurred.astype(np.float32) - expected)
    print(f"defocus {diameter:.2f} px: max {diff.max():.2f}, mean {diff.mean():.3f} grey levels")
    assert diff.max() <= 1.5 and diff.mean() < 0.1


def test_vignetting_reaches_the_corner_illumination():
    # The top-left corner, the principal point and the corner's mirror image through it.
    c = np.array([PINHOLE.cx, PINHOLE.cy])
    xy = PINHOLE.unproject(np.array([[0.0, 0.0], c, 2 * c]))
    r2 = float(np.sum(xy[0] ** 2))
    g = vignetting_gain(xy, 0.6, r2)
    assert g[0] == pytest.approx(0.6, rel=1e-6) and g[2] == pytest.approx(0.6, rel=1e-6)
    assert g[1] == pytest.approx(1.0)
    # corner_illumination = cos^4 of the corner's angle is the natural law (exponent 1).
    natural = (1 / (1 + r2)) ** 2
    assert vignetting_gain(xy, natural, r2)[0] == pytest.approx(natural, rel=1e-6)


def test_lens_defocus_leaves_corners_unbiased(rays):
    """A tilted board is blurred more at one end than the other; the corners stay where the
    truth puts them to a few hundredths of a pixel (symmetric blur per corner)."""
    optics = Optics(f_number=2.0, focal_length_mm=6.0, focus_distance_mm=300.0)
    R, t = tilted(depth=420.0)
    img = AnalyticRenderer(PINHOLE, BOARD, RenderSettings(optics=optics),
                           rays(PINHOLE)).render(R, t)
    truth = project(PINHOLE, R, t, OBJ)
    err = detect(img, truth) - truth
    print(f"defocused corners: mean |e| {np.linalg.norm(err, axis=1).mean():.4f} px, "
          f"bias {err.mean(0)}")
    assert np.linalg.norm(err, axis=1).mean() < 0.06 and np.abs(err.mean(0)).max() < 0.03


# --- motion -----------------------------------------------------------------------------------
@pytest.mark.parametrize("direction", [(1.0, 0.0), (0.0, 1.0)])
def test_linear_motion_is_a_box_filter(rays, direction):
    """A fronto-parallel board sliding sideways (or up) at constant depth moves the image by
    s = fx v T / z: its motion blur is the sharp image convolved with a box of length s."""
    depth, speed, exposure_ms = 400.0, 400.0, 20.0
    s = PINHOLE.fx * speed * exposure_ms / 1000 / depth  # 12 px
    R, t = frontal(depth)
    sharp = AnalyticRenderer(PINHOLE, BOARD, RenderSettings(), rays(PINHOLE)).render(R, t)
    moving = AnalyticRenderer(PINHOLE, BOARD, RenderSettings(motion=Motion(exposure_ms, speed)),
                              rays(PINHOLE))
    velocity = (np.zeros(3), speed * np.array([*direction, 0.0]))
    img = moving.render(R, t, velocity=velocity)
    # The continuous box of length s with fractional end taps.
    n = int(np.ceil(s / 2))
    taps = np.clip(s / 2 - np.abs(np.arange(-n, n + 1)) + 0.5, 0, 1)
    box = (taps / taps.sum()).astype(np.float32)[None, :]
    if direction[1]:
        box = box.T
    expected = cv2.filter2D(sharp.astype(np.float32), -1, box, borderType=cv2.BORDER_REPLICATE)
    diff = np.abs(img.astype(np.float32) - expected)
    subframes = len(moving._exposure_poses(R, t, velocity))
    print(f"motion of {s:.1f} px in {subframes} sub-frames: max {diff.max():.2f}, "
          f"mean {diff.mean():.3f} grey levels")
    assert diff.mean() < 0.5 and diff.max() < 8


@pytest.mark.parametrize("s", [1, 2, 3, 4])
def test_each_subframe_samples_every_row_and_column_of_the_pixel(s):
    """The exposure's samples (time_area_offsets): s per sub-frame, one in each row and each
    column of the s x s grid (so their mean is the pixel's centre at every instant), and s
    consecutive sub-frames cover the grid's s^2 cells once."""
    grid = (np.arange(s) + 0.5) / s - 0.5
    offsets = time_area_offsets(3 * s + 1, s)
    assert offsets.shape == (3 * s + 1, s, 2)
    for sub in offsets:
        assert sorted(sub[:, 0]) == pytest.approx(grid) and sorted(sub[:, 1]) == pytest.approx(grid)
    for i in range(len(offsets) - s + 1):
        cells = {(round((du + 0.5) * s - 0.5), round((dv + 0.5) * s - 0.5))
                 for du, dv in offsets[i:i + s].reshape(-1, 2)}
        assert len(cells) == s * s


def test_motion_bands_are_exact_wherever_a_cell_they_span_is_rough():
    """A sub-frame draws consecutive smooth strips as one band over their widest columns; the
    band interpolates texel coordinates only if none of the cells it spans is rough (a plane's
    horizon beside the board would otherwise be interpolated across)."""
    from stereo_bench.render.analytic import _CELL, _bands
    rough = np.zeros((3, 4), np.uint8)
    strips = [(0, _CELL, 0, 2 * _CELL, False), (_CELL, 2 * _CELL, 2 * _CELL, 4 * _CELL, False),
              (2 * _CELL, 3 * _CELL, 0, _CELL, True)]
    smooth, edge = _bands(strips, rough)
    assert smooth == (0, 2 * _CELL, 0, 4 * _CELL, False) and edge == strips[2]
    rough[0, 3] = 1  # beside the first strip, inside the band's columns
    assert _bands(strips, rough)[0] == (0, 2 * _CELL, 0, 4 * _CELL, True)


def test_the_warps_shift_over_an_exposure_is_quadratic_in_time(rays):
    """An exposure computes the board-as-made's texel shift at three sub-frames and
    interpolates it for the others: within 1e-3 px of the shift computed at every sub-frame,
    for a bowed, misprinted board turning and moving fast (25 px of motion)."""
    from stereo_bench.render.analytic import _lagrange
    shape = BoardShape.for_pattern(BOARD, aspect_error_pct=0.2, warp_mm=(1.6, 1.0))
    renderer = AnalyticRenderer(PINHOLE, BOARD, RenderSettings(motion=Motion(33.0, 1.0),
                                                                board=shape), rays(PINHOLE))
    R, t = tilted(depth=420.0)
    velocity = (np.array([1.5, -1.0, 2.0]), np.array([250.0, 150.0, 100.0]))
    poses = renderer._exposure_poses(R, t, velocity)
    k = len(poses)
    view = renderer.rays.toward(OBJ @ R.T + t)
    seen = [renderer._seen(Rk, tk, view) for Rk, tk in poses]
    level = renderer._level(max(x.footprint for x in seen) / 2, True, R, t)
    shifts = [renderer._warp_shift(level, x.B, x.R, x.t) for x in seen]
    r0, r1, c0, c1, _ = seen[k // 2].strips[len(seen[k // 2].strips) // 2]
    xy = view.xy[r0:r1 + 2, c0:c1 + 2]
    keys = [0, k // 2, k - 1]
    at_keys = [shifts[i](xy) for i in keys]
    times = (np.arange(k) + 0.5) / k
    texels = renderer._texel_map(level, seen[k // 2].B, seen[k // 2].R, seen[k // 2].t)(xy, False)
    texel_px = 1 / min(np.linalg.norm(np.diff(texels, axis=a), axis=-1).min() for a in (0, 1))
    err = max(np.abs(sum(w * a for w, a in zip(_lagrange(times[keys], times[i]), at_keys))
                     - shifts[i](xy)).max() for i in range(k))
    moved = np.abs(at_keys[2] - at_keys[0]).max()
    print(f"{k} sub-frames: the shift moves {moved * texel_px:.3f} px, interpolated within "
          f"{err * texel_px:.2e} px")
    assert k == 32 and moved * texel_px > 0.01 and err * texel_px < 1e-3


def test_motion_blur_keeps_the_truth_at_mid_exposure(rays):
    R, t = tilted(depth=420.0)
    omega, v = np.array([0.0, 0.0, 1.0]), np.array([150.0, 80.0, 0.0])  # rad/s, mm/s
    renderer = AnalyticRenderer(PINHOLE, BOARD, RenderSettings(motion=Motion(8.0, 1.0)),
                                rays(PINHOLE))
    img = renderer.render(R, t, velocity=(omega, v))
    truth = project(PINHOLE, R, t, OBJ)
    err = np.linalg.norm(detect(img, truth) - truth, axis=1)
    print(f"motion-blurred corners: mean {err.mean():.4f} px, max {err.max():.4f} px")
    assert err.mean() < 0.05


# --- sensor -----------------------------------------------------------------------------------
@pytest.mark.parametrize("exposure", [0.5, 0.05])
def test_sensor_noise_follows_the_photon_transfer_curve(exposure):
    sensor = Sensor(full_well_e=10000.0, exposure=exposure, read_noise_e=5.0)
    irradiance = np.full((400, 400), 110.0, dtype=np.float32)
    img = expose(irradiance, sensor, 235.0, noise_draws(np.random.default_rng(0),
                                                        irradiance.shape))
    e_per_dn = exposure * 10000.0 / 235.0
    electrons = 110.0 * e_per_dn
    sigma = np.sqrt(electrons + 25.0) / e_per_dn
    measured = img.astype(float).std()
    # The 8-bit rounding adds a uniform error of variance 1/12.
    assert measured == pytest.approx(np.sqrt(sigma**2 + 1 / 12), rel=0.02)
    assert img.mean() == pytest.approx(110.0, abs=0.05)


def test_sensor_saturates_adc_quantizes_and_jpeg_is_a_round_trip():
    ramp = np.tile(np.linspace(0, 250, 256, dtype=np.float32), (64, 1))
    bright = expose(ramp, Sensor(gain=2.0), 235.0, None)
    assert bright.max() == 255 and np.all(bright[:, -20:] == 255)
    coarse = expose(ramp, Sensor(adc_bits=4), 235.0, None)
    assert len(np.unique(coarse)) <= 16
    lossless = expose(ramp, Sensor(), 235.0, None)
    jpeg = expose(ramp, Sensor(jpeg_quality=40), 235.0, None)
    ok, buf = cv2.imencode(".jpg", lossless, [cv2.IMWRITE_JPEG_QUALITY, 40])
    assert np.array_equal(jpeg, cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE))


@pytest.mark.parametrize("sensor", [
    Sensor(full_well_e=6000.0, exposure=0.3, read_noise_e=3.0, gain=1.4, noise_sigma=0.7),
    Sensor(full_well_e=900.0, exposure=0.9, gain=2.5, adc_bits=5),
    Sensor(noise_sigma=3.0, gain=1.2, adc_bits=6), Sensor(gain=1.7)])
def test_the_compiled_sensor_is_the_photon_transfer_model_in_float32(sensor):
    """expose's one compiled pass gives, byte for byte, the photon transfer model written as
    numpy float32 operations (each rounded as numpy rounds it): electrons, the noise's sd from
    shot, read and additive noise, the full well after the noise, the ADC, rounding half to
    even and saturation to 8 bits; over a ramp from below black to past saturation."""
    f32 = np.float32
    irradiance = np.tile(np.linspace(-20, 400, 640, dtype=np.float32), (48, 1))
    draws = noise_draws(np.random.default_rng(2), irradiance.shape)
    noise = NORMAL_QUANTILES[draws]
    if sensor.full_well_e is not None:
        e_per_dn = sensor.exposure * sensor.full_well_e / 235.0
        to_dn = sensor.gain / e_per_dn
        electrons = np.maximum(irradiance * f32(e_per_dn), f32(0))
        var = electrons * f32(to_dn ** 2)
        var += f32((sensor.read_noise_e * to_dn) ** 2 + sensor.noise_sigma ** 2)
        dn = electrons * f32(to_dn) + np.sqrt(var) * noise
        dn = np.minimum(dn, f32(sensor.full_well_e * to_dn))
    else:
        dn = irradiance * f32(sensor.gain)
        if sensor.noise_sigma > 0:
            dn = dn + f32(sensor.noise_sigma) * noise
    if sensor.adc_bits < 8:
        step = f32(256.0 / (1 << sensor.adc_bits))
        dn = np.floor(np.clip(dn, f32(0), f32(255.999)) / step) * step + f32(step / 2)
    expected = np.clip(np.rint(dn), 0, 255).astype(np.uint8)
    assert np.array_equal(expose(irradiance, sensor, 235.0, draws if sensor.noisy else None),
                          expected)


@pytest.mark.parametrize("sensor", [
    Sensor(full_well_e=6000.0, exposure=0.3, read_noise_e=3.0, gain=1.4, jpeg_quality=85),
    Sensor(noise_sigma=3.0, adc_bits=6)])
def test_the_sensor_on_the_boards_box_is_the_sensor_on_the_whole_frame(rays, sensor):
    """The renderer filters only the board's box per frame and exposes it with the (vignetted)
    background around it in one pass: byte for byte the whole-frame sensor on the same noise
    draws."""
    settings = RenderSettings(optics=Optics(corner_illumination=0.6), sensor=sensor)
    renderer = AnalyticRenderer(WIDE, BOARD, settings, rays(WIDE))
    R, t = tilted(depth=500.0)
    img = renderer.render(R, t, np.random.default_rng(5))
    canvas = np.full((WIDE.height, WIDE.width), round(110.0 * 256), np.uint16)
    strips = renderer._draw_board(canvas, R, t, renderer.rays.toward(OBJ @ R.T + t))
    assert 0 < sum((r1 - r0) * (c1 - c0) for r0, r1, c0, c1, _ in strips) < canvas.size / 2
    irradiance = canvas.astype(np.float32) * np.float32(1 / 256)
    irradiance *= vignetting_map(rays(WIDE).xy[1:-1, 1:-1], 0.6)
    draws = noise_draws(np.random.default_rng(5), canvas.shape)
    assert np.array_equal(img, expose(irradiance, sensor, 235.0, draws))


def test_photograph_records_each_colour_channel_as_a_sensor_of_its_own():
    """A body frame (colour) through a camera: each channel's noise follows the photon transfer
    curve of its own level, and a clean camera records the image as it is."""
    image = np.zeros((300, 300, 3), np.float32)
    image[...] = (40.0, 110.0, 200.0)
    assert np.array_equal(photograph(image, Optics(), Sensor(), 235.0, None, None),
                          image.astype(np.uint8))
    sensor = Sensor(full_well_e=6000.0, exposure=0.2, read_noise_e=3.0)
    out = photograph(image, Optics(), sensor, 235.0, None, np.random.default_rng(0))
    e_per_dn = 0.2 * 6000.0 / 235.0
    for c, level in enumerate((40.0, 110.0, 200.0)):
        sigma = np.sqrt(level * e_per_dn + 9.0) / e_per_dn
        assert out[..., c].astype(float).std() == pytest.approx(np.sqrt(sigma ** 2 + 1 / 12),
                                                                rel=0.03)
        assert out[..., c].mean() == pytest.approx(level, abs=0.1)
    with pytest.raises(ValueError, match="a noisy sensor needs an rng"):
        photograph(image, Optics(), sensor, 235.0, None, None)
    # JPEG in colour: the decoded image is the colour round trip of the lossless one.
    ramp = np.dstack([np.tile(np.linspace(0, 250, 64, dtype=np.float32), (64, 1))] * 3)
    jpeg = photograph(ramp, Optics(), Sensor(jpeg_quality=50), 235.0, None, None)
    ok, buf = cv2.imencode(".jpg", np.rint(ramp).astype(np.uint8), [cv2.IMWRITE_JPEG_QUALITY, 50])
    assert np.array_equal(jpeg, cv2.imdecode(buf, cv2.IMREAD_COLOR))


def test_photograph_applies_the_renderers_vignetting_and_a_uniform_defocus():
    W = 201
    u = (np.arange(W) - 100) / 100.0
    xy = np.stack(np.meshgrid(u, u), -1).astype(np.float32)
    flat = np.full((W, W), 200.0, np.float32)
    optics = Optics(corner_illumination=0.5)
    out = photograph(flat, optics, Sensor(), 235.0, camera_vignette(xy, optics), None)
    assert np.array_equal(out, np.rint(200.0 * vignetting_map(xy, 0.5)).astype(np.uint8))
    assert out[0, 0] == round(100.0) and out[100, 100] == 200
    # A point of light spreads over the disc of the defocus radius, its total kept.
    dot = np.zeros((W, W), np.float32)
    dot[100, 100] = 255.0 * 50
    blurred = photograph(dot, Optics(), Sensor(), 235.0, None, None, defocus_px=4.0).astype(float)
    assert blurred.sum() == pytest.approx(255.0 * 50, rel=0.03)
    rows, cols = np.nonzero(blurred)
    assert max(np.abs(rows - 100).max(), np.abs(cols - 100).max()) == 4


# --- light ------------------------------------------------------------------------------------
def test_specular_peak_is_at_the_mirror_point():
    """The lamp behind the camera on the normal through the board point: the directions to the
    lamp and to the camera coincide with the normal, n . h = 1, so the highlight is
    ``specular`` (times the falloff, 1 at the reference point) and Lambert's cosine is 1."""
    point = np.array([[0.0, 0.0, 500.0]])
    normal = np.array([0.0, 0.0, -1.0])
    lamp = np.array([0.0, 0.0, -300.0])
    light = Light(ambient=0.3, specular=0.4, shininess=80.0)
    diffuse, spec = blinn_phong(point, normal, lamp, light, point[0])
    assert spec[0] == pytest.approx(0.4, rel=1e-9)
    assert diffuse[0] == pytest.approx(1.0, rel=1e-9)
    off = np.array([[150.0, 0.0, 500.0]])
    assert blinn_phong(off, normal, lamp, light, point[0])[1][0] < 0.1 * 0.4


def test_a_glossy_highlight_brightens_the_black_print(rays):
    R, t = frontal(depth=400.0)
    light = Light(direction=(0.0, 0.0, 1.0), distance_mm=400.0, ambient=0.5, specular=0.6,
                  shininess=20.0)
    lit = AnalyticRenderer(PINHOLE, BOARD, RenderSettings(light=light), rays(PINHOLE))
    img = lit.render(R, t)
    plain = AnalyticRenderer(PINHOLE, BOARD, RenderSettings(light=Light(
        direction=(0.0, 0.0, 1.0), distance_mm=400.0, ambient=0.5)), rays(PINHOLE)).render(R, t)
    centre = (slice(200, 280), slice(280, 360))  # the highlight: lamp behind the camera
    assert img[centre].min() > plain[centre].min() + 40  # the black squares wash out


# --- presets and configuration ----------------------------------------------------------------
QUICKSTART = "configs/quickstart.yaml"


def test_presets_fill_what_the_file_leaves_and_the_file_wins():
    base = load_rig(QUICKSTART).model_dump(mode="json")
    for kind, preset in PRESETS.items():
        cfg = parse_rig({**base, "environment": {"kind": kind}})
        env = cfg.environment.model_dump(mode="json")
        for section, values in preset.settings.items():
            for key, value in values.items():
                got = env[section][key]
                assert (list(got) if isinstance(got, (list, tuple)) else got) == value, \
                    (kind, section, key)
        # The resolved configuration reads back to itself.
        again = parse_rig(cfg.model_dump(mode="json"))
        assert again == cfg
    mine = parse_rig({**base, "environment": {"kind": "office", "sensor": {"jpeg_quality": 95}}})
    assert mine.environment.sensor.jpeg_quality == 95
    assert mine.environment.sensor.full_well_e == PRESETS["office"].settings["sensor"][
        "full_well_e"]


@pytest.mark.parametrize("env, match", [
    ({"kind": "foggy"}, "environment.kind: .*unknown environment 'foggy'.*office"),
    ({"kind": ["office"]}, "environment.kind"),
    ({"kind": "office", "sensor": [1, 2]}, "environment.sensor"),
    ({"kind": "clean", "noise_sigma": 3}, "noise_sigma: now environment.sensor.noise_sigma"),
    ({"optics": {"f_number": 2.0, "focal_length_mm": 50.0, "focus_distance_mm": 40.0}},
     "focus_distance_mm"),
    ({"board": {"warp_mm": [500, 0]}}, "environment.board.warp_mm"),
    ({"sensor": {"jpeg_quality": 0}}, "environment.sensor.jpeg_quality"),
])
def test_bad_environment_names_the_field(env, match):
    base = load_rig(QUICKSTART).model_dump(mode="json")
    with pytest.raises(ConfigError, match=match):
        parse_rig({**base, "environment": env}, "rig.yaml")


def test_board_velocity_moves_the_fastest_corner_at_the_speed():
    """Moving for the time its fastest corner needs to cover the step to the next frame at the
    speed, the board (turned about its centre, its centre moved) reaches the next frame."""
    from stereo_bench.scene.rig import Rig
    rig = Rig.from_config(load_rig(QUICKSTART))
    cam = rig.cameras[0]
    omega, v = rig.board_velocity(cam, 250.0)
    R, t = rig.cam_from_board(cam)
    x0, y0 = BOARD.texture_origin_mm
    w, h = BOARD.size_mm
    outline = np.array([[x0, y0, 0], [x0 + w, y0, 0], [x0 + w, y0 + h, 0], [x0, y0 + h, 0.0]])
    for f in (0, 10, len(R) - 2):
        step = np.linalg.norm((outline @ R[f + 1].T + t[f + 1]) - (outline @ R[f].T + t[f]),
                              axis=1).max()
        T = step / 250.0
        assert np.allclose(rodrigues_to_matrix(omega[f] * T) @ R[f], R[f + 1], atol=1e-9)
        centre = R[f] @ rig.board_centre + t[f]
        assert np.allclose(centre + v[f] * T, R[f + 1] @ rig.board_centre + t[f + 1], atol=1e-9)
    # The last frame takes the step that led to it.
    assert np.allclose(omega[-1], omega[-1]) and np.linalg.norm(v[-1]) > 0


def test_board_speed_along_a_session_follows_the_hand():
    """speed: trajectory: a session's frames are evenly spaced in time, so each frame's
    fastest corner moves at the given mean speed times its step over the mean step of its
    sequence (the walk, each close-up): the same directions, speeds in the steps' ratios."""
    from stereo_bench.scene.rig import Rig
    rig = Rig.from_config(load_rig(Path(QUICKSTART).parent / "studios" / "h36m_rectangle.yaml"))
    cam = rig.cameras[0]
    omega_c, v_c = rig.board_velocity(cam, 150.0)
    omega, v = rig.board_velocity(cam, 150.0, along_trajectory=True)
    ratio = np.linalg.norm(v, axis=1) / np.linalg.norm(v_c, axis=1)  # this frame's / 150
    assert np.allclose(omega, omega_c * ratio[:, None], atol=1e-12)
    R, t = rig.trajectory.rotations, rig.trajectory.tvecs
    corners = np.einsum("fij,kj->fki", R[:, :, :2], rig.pattern.outline_mm()) + t[:, None]
    walk = np.flatnonzero(rig.closeup_of == -1)
    step = np.linalg.norm(np.diff(corners[walk], axis=0), axis=2).max(axis=1)
    assert np.allclose(ratio[walk[:-1]], step / np.append(step, step[-1]).mean(), rtol=1e-9)
    assert ratio[walk].mean() == pytest.approx(1.0, rel=1e-9)
    assert ratio[walk].max() / ratio[walk].min() > 1.5  # a session's hand does not keep pace


def test_the_board_as_made_is_exact_between_its_grid_nodes(rays):
    """The smooth texel map of a warped, misprinted board is exact on a grid of 4 px and
    linear in between, on top of the exact plane map. Against the exact intersection at every
    pixel, the error in image pixels (texels over texels per pixel) stays below 0.008 px on
    the wide-angle camera, for an extreme 5 mm warp of a 135 x 180 mm board as for a 1.5 mm one
    (what remains is the lens's and the perspective's curvature over 4 px, times the 1.5 %
    misprint), against 0.016 px of the clean checkerboard's detection error."""
    from stereo_bench.render.analytic import _PAD
    R, t = tilted(depth=380.0)
    B = np.linalg.inv(np.column_stack([R[:, 0], R[:, 1], t]))
    for warp in ((5.0, -4.0), (1.5, 1.0)):
        shape = BoardShape.for_pattern(BOARD, scale_error_pct=1.5, aspect_error_pct=1.0,
                                       warp_mm=warp)
        renderer = AnalyticRenderer(WIDE, BOARD, RenderSettings(board=shape), rays(WIDE))
        level = renderer._rasterize(8.0)
        to_texels = renderer._texel_map(level, B, R, t)
        xy = rays(WIDE).xy[150:260, 250:420]
        interpolated, exact = to_texels(xy, False), to_texels(xy, True)
        inside = np.all((exact > _PAD) & (exact < np.array(level.image.shape[::-1]) - _PAD), -1)
        texels_per_px = np.linalg.norm(np.diff(exact, axis=1), axis=-1)[inside[:, 1:]].mean()
        err_px = np.linalg.norm(interpolated - exact, axis=-1)[inside].max() / texels_per_px
        print(f"warp {warp} mm: interpolated texel map off by at most {err_px:.5f} px")
        assert inside.mean() > 0.5 and err_px < 0.008


@pytest.mark.parametrize("sigma", [0.5, 2.0, 6.0, 32.0])
def test_noisy_levels_equal_opencvs_weighted_sum_of_the_same_draws(sigma):
    """The compiled integer path of additive noise gives, pixel for pixel, OpenCV's float32
    weighted sum (rounded half to even, saturated) of the same draws, and leaves the rng where
    the noise image would."""
    from stereo_bench.render.texels import noisy_levels
    canvas = np.random.default_rng(9).integers(0, 1 << 16, (480, 640)).astype(np.uint16)
    canvas[:8] = 0  # black and white rows, where the noise saturates
    canvas[8:16] = 0xFFFF
    a, b = np.random.default_rng(4), np.random.default_rng(4)
    expected = cv2.addWeighted(canvas, 1 / 256, NORMAL_QUANTILES[noise_draws(a, canvas.shape)],
                               sigma, 0, dtype=cv2.CV_8U)
    assert np.array_equal(noisy_levels(b, canvas, sigma), expected)
    assert a.integers(1 << 30) == b.integers(1 << 30)


@pytest.mark.parametrize("shape", [(480, 640), (4, 4), (3, 5), (1,)])
@pytest.mark.parametrize("before", ["nothing", "a normal", "a 32-bit integer"])
def test_noise_draws_are_the_generators_16_bit_integers(shape, before):
    """noise_draws reads the generator's raw words where it can (a count that is a multiple of
    four, no half-used word): the draws are rng.integers' all the same, and the generator goes
    on alike, whatever was drawn from it before."""
    a, b = np.random.default_rng([0, 1, 2]), np.random.default_rng([0, 1, 2])
    for rng in (a, b):
        if before == "a normal":
            rng.normal(size=3)
        elif before == "a 32-bit integer":  # leaves half of a 64-bit word
            rng.integers(0, 1 << 32, dtype=np.uint32)
    draws = noise_draws(b, shape)
    assert draws.dtype == np.uint16 and draws.shape == shape
    assert np.array_equal(draws, a.integers(0, 1 << 16, size=shape, dtype=np.uint16))
    assert np.array_equal(a.integers(0, 1 << 16, 9, dtype=np.uint16),
                          b.integers(0, 1 << 16, 9, dtype=np.uint16))
    assert a.normal() == b.normal()


def test_grid_interpolation_is_linear_between_its_nodes_in_each_axis():
    """The board as made's shift is exact on a grid of nodes and linear in between
    (texels.grid_interpolation): np.interp along the rows, then the columns, in float64, within
    float32 rounding; exact at the nodes (but the last row's and column's, reached as the end
    of their interval)."""
    from stereo_bench.render.texels import grid_interpolation
    h, w = 37, 53
    rows, cols = np.array([0, 4, 9, 13, 17, 22, 26, 31, 36]), np.arange(0, w, 4)
    values = np.random.default_rng(1).normal(size=(len(rows), len(cols), 2)).astype(np.float32)
    out = grid_interpolation(values, rows, cols, h, w)
    along_rows = np.stack([[np.interp(np.arange(h), rows, values[:, j, c]) for j in
                            range(len(cols))] for c in range(2)], -1).transpose(1, 0, 2)
    expected = np.stack([[np.interp(np.arange(w), cols, along_rows[i, :, c]) for i in range(h)]
                         for c in range(2)], -1)
    assert out.shape == (h, w, 2) and np.abs(out - expected).max() < 1e-5
    assert np.array_equal(out[np.ix_(rows[:-1], cols[:-1])], values[:-1, :-1])
