"""The analytic renderer against exact ground truth.

Run with ``pytest -s`` to see the measured corner errors.
"""

import cv2
import numpy as np
import pytest

from render_scene import (BOARD, CENTRE, OBJ, PINHOLE, RECT_QUARTER, SUBPIX, WIDE,
                          detect, tilted_poses)
from stereo_bench.core.camera import Camera
from stereo_bench.core.poses import rodrigues_to_matrix
from stereo_bench.render import AnalyticRenderer, RenderSettings
from stereo_bench.render.texels import plane_texels, sample_texels
from stereo_bench.render.imaging import Light, Optics, Sensor


@pytest.mark.parametrize("cam", [WIDE, RECT_QUARTER], ids=lambda c: c.name)
def test_detected_corners_match_ground_truth(cam, rays):
    """Geometry is exact: corners detected in renders of tilted, distorted views sit where the
    camera model projects the board's corners (the detector's own error included)."""
    for blur in (0.0, 0.5):
        renderer = AnalyticRenderer(cam, BOARD, RenderSettings(optics=Optics(blur_px=blur)),
                                    rays(cam))
        errors = []
        for R, t in tilted_poses(cam, 12, seed=3):
            truth = cam.project_cam(OBJ @ R.T + t)
            errors.append(detect(renderer.render(R, t), truth) - truth)
        e = np.concatenate(errors)
        d = np.linalg.norm(e, axis=1)
        print(f"\n{cam.name} blur {blur} px, {len(errors)} views x {len(OBJ)} corners: "
              f"mean {d.mean():.4f} px, max {d.max():.4f} px, "
              f"signed mean ({e[:, 0].mean():+.4f}, {e[:, 1].mean():+.4f}) px")
        assert d.mean() < 0.05
        assert np.all(np.abs(e.mean(0)) < 0.01)


@pytest.mark.parametrize("s", [2, 4])
def test_matches_ideal_sensor(s, rays):
    """Detector-independent: a fronto-parallel pinhole view is an exact scaling of the texture,
    so the ideal sensor image (box filter over each pixel) is the pattern's exact area coverage
    at 4 texels per pixel, averaged over 4 x 4 blocks. Corners found by the same detector in the
    render and in the ideal image agree far better than the detector's own error (~0.08 px on
    such sharp images)."""
    F, z = 4, 400.0
    settings = RenderSettings(supersampling=s)
    renderer = AnalyticRenderer(PINHOLE, BOARD, settings, rays(PINHOLE))
    cover = BOARD.texture(F * PINHOLE.fx / z).astype(np.float32) / 255
    h, w = cover.shape
    deltas, pixels = [], []
    for pu, pv in [(1, 3), (3, 2), (2, 1), (0, 3)]:  # outline phase in 1/4 px
        ku, kv = 100, 40
        left = (ku - 0.5 + pu / F - PINHOLE.cx) * z / PINHOLE.fx
        top = (kv - 0.5 + pv / F - PINHOLE.cy) * z / PINHOLE.fy
        t = np.array([left, top, z]) - np.append(BOARD.texture_origin_mm, 0)
        img = renderer.render(np.eye(3), t)
        fine = np.zeros((PINHOLE.height * F, PINHOLE.width * F), np.float32)
        fine[kv * F + pv:kv * F + pv + h, ku * F + pu:ku * F + pu + w] = cover
        coverage = fine.reshape(PINHOLE.height, F, PINHOLE.width, F).mean((1, 3))
        ideal = np.rint(settings.black_level
                        + (settings.white_level - settings.black_level) * coverage)
        truth = PINHOLE.project_cam(OBJ + t).astype(np.float32).reshape(-1, 1, 2)
        found = [cv2.cornerSubPix(im.astype(np.uint8), truth.copy(), (5, 5), (-1, -1), SUBPIX)
                 for im in (img, ideal)]
        deltas.append((found[0] - found[1]).reshape(-1, 2))
        inner = (slice(kv + 2, kv + h // F - 2), slice(ku + 2, ku + w // F - 2))
        pixels.append((img[inner] - ideal[inner]).ravel())
    d, p = np.concatenate(deltas), np.concatenate(pixels)
    dist = np.linalg.norm(d, axis=1)
    print(f"\ns={s}: corners(render) - corners(ideal): mean {dist.mean():.4f} px, max "
          f"{dist.max():.4f} px, signed ({d[:, 0].mean():+.5f}, {d[:, 1].mean():+.5f}) px; "
          f"pixels RMS {np.sqrt(np.mean(p * p)):.2f} gray levels")
    assert dist.mean() < 0.02
    assert np.all(np.abs(d.mean(0)) < 0.002)


@pytest.mark.parametrize("cam", [WIDE, RECT_QUARTER], ids=lambda c: c.name)
@pytest.mark.parametrize("s", [2, 4])
def test_interpolated_samples_match_exact_rays(cam, s, rays):
    """Sub-pixel samples are interpolated from the exact per-pixel rays: compare with
    Camera.unproject at every sample, through a homography whose output is in pixel-like units
    (board mm * f / z)."""
    R = rodrigues_to_matrix([0.5, -0.3, 0.2])
    t = np.array([-30.0, 20.0, 300.0])
    M = np.diag([cam.fx / 300, cam.fx / 300, 1.0]) @ np.linalg.inv(
        np.column_stack([R[:, 0], R[:, 1], t]))
    r0, r1 = 100, 164
    offsets = (np.arange(s) + 0.5) / s - 0.5
    u = (np.arange(cam.width)[:, None] + offsets).ravel()
    v = (np.arange(r0, r1)[:, None] + offsets).ravel()
    q = np.concatenate([cam.unproject(np.stack(np.meshgrid(u, v), -1)),
                        np.ones((len(v), len(u), 1))], -1) @ M.T
    truth = q[..., :2] / q[..., 2:]
    for per_sample in (False, True):
        err = sample_texels(rays(cam).xy[r0:r1 + 2], plane_texels(M), s, per_sample) - truth
        assert np.abs(err).max() < 1e-3
        assert np.all(np.abs(err.reshape(-1, 2).mean(0)) < 5e-4)


def ray_hits(cam, R, t):
    """(H, W) bool for every pixel centre: does its ray hit the board in front of the camera?
    Computed from Camera.unproject, independently of the renderer."""
    xy = cam.unproject(cam.pixel_grid())
    q = np.concatenate([xy, np.ones(xy.shape[:-1] + (1,))], -1) @ np.linalg.inv(
        np.column_stack([R[:, 0], R[:, 1], t])).T
    X, Y = q[..., 0] / q[..., 2], q[..., 1] / q[..., 2]
    (x0, y0), (w, h) = BOARD.texture_origin_mm, BOARD.size_mm
    return (q[..., 2] > 0) & (X > x0) & (X < x0 + w) & (Y > y0) & (Y < y0 + h)


def away_from_outline(mask):
    """Pixels of mask at least 2 px (chessboard distance) inside it: off the anti-aliased
    outline. The pixel box reaches 0.5 px past an edge and the texture's prefilter (texel box
    and bilinear tent, about one sample wide) 0.75 px more at s = 2; more where the board is
    nearer than the point whose footprint chose the texture level (one level per frame)."""
    return cv2.erode(mask.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0


def test_same_seed_same_bytes_and_noise_level(rays):
    noisy = AnalyticRenderer(WIDE, BOARD, RenderSettings(light=Light(ambient=0.35),
                                                        sensor=Sensor(noise_sigma=6.0)),
                             rays(WIDE))
    R, t = tilted_poses(WIDE, 1, seed=7)[0]
    a = noisy.render(R, t, np.random.default_rng(11))
    b = noisy.render(R, t, np.random.default_rng(11))
    c = noisy.render(R, t, np.random.default_rng(12))
    assert a.dtype == np.uint8 and a.shape == (WIDE.height, WIDE.width)
    assert a.tobytes() == b.tobytes()
    assert a.tobytes() != c.tobytes()
    clean = AnalyticRenderer(WIDE, BOARD, RenderSettings(), rays(WIDE))
    assert clean.render(R, t).tobytes() == clean.render(R, t, np.random.default_rng(1)).tobytes()
    # The background is flat, so what varies there is the noise alone.
    off = away_from_outline(~ray_hits(WIDE, R, t))
    assert abs(np.std(a[off].astype(float)) - 6.0) < 0.2


def test_noisy_light_shades_the_board_smoothly(rays):
    R, t = tilted_poses(WIDE, 1, seed=7)[0]
    lit = AnalyticRenderer(WIDE, BOARD, RenderSettings(light=Light(ambient=0.35)),
                           rays(WIDE)).render(R, t)
    clean = AnalyticRenderer(WIDE, BOARD, RenderSettings(), rays(WIDE)).render(R, t)
    white = clean == RenderSettings().white_level
    gain = lit[white] / RenderSettings().white_level
    assert 0.35 < gain.min() < gain.max() < 1.2 and gain.max() - gain.min() > 0.05
    off = away_from_outline(~ray_hits(WIDE, R, t))
    assert np.all(lit[off] == clean[off])  # the background is not lit


@pytest.mark.parametrize("case", ["small", "straddling", "behind", "edge_on", "back_side"])
def test_pixels_off_the_board_are_background(case, rays):
    settings = RenderSettings(background=5)  # below the black print: no board pixel equals it
    renderer = AnalyticRenderer(WIDE, BOARD, settings, rays(WIDE))
    R = rodrigues_to_matrix([0.3, -0.2, 0.1])
    if case == "small":
        t = np.array([60.0, -40.0, 1500.0]) - R @ CENTRE
    elif case == "straddling":  # tilted 68 degrees, centre behind the camera, one end in front
        R = rodrigues_to_matrix([0.28, -1.15, 0])
        t = np.array([0.0, -40.0, -20.0]) - R @ CENTRE
        (x0, y0), (w, h) = BOARD.texture_origin_mm, BOARD.size_mm
        depth = (np.array([[x0, y0, 0], [x0 + w, y0 + h, 0]]) @ R.T + t)[:, 2]
        assert depth.min() < 0 < depth.max()
    elif case == "behind":
        t = np.array([0.0, 0.0, -400.0]) - R @ CENTRE
    elif case == "edge_on":  # the board plane contains the camera centre
        R = rodrigues_to_matrix([0, np.pi / 2, 0])
        t = np.array([0.0, 0.0, 400.0]) - R @ CENTRE
    else:  # the printed side faces away: the blank back is seen
        R = rodrigues_to_matrix([0, np.pi, 0])
        t = np.array([0.0, 0.0, 400.0]) - R @ CENTRE
    img = renderer.render(R, t)
    if case in ("behind", "edge_on"):
        assert np.all(img == settings.background)
        return
    hits = ray_hits(WIDE, R, t)
    inside, outside = away_from_outline(hits), away_from_outline(~hits)
    assert inside.any() and outside.any()
    assert np.all(img[outside] == settings.background)
    assert np.all(img[inside] != settings.background)
    if case == "back_side":
        assert np.all(img[inside] == settings.white_level)


def test_bad_input_names_the_field():
    with pytest.raises(ValueError, match="sensor"):
        RenderSettings(sensor="noisy")
    with pytest.raises(ValueError, match="supersampling"):
        RenderSettings(supersampling=0)
    with pytest.raises(ValueError, match="black_level"):
        RenderSettings(black_level=240)
    renderer = AnalyticRenderer(PINHOLE, BOARD, RenderSettings(sensor=Sensor(noise_sigma=6.0)))
    with pytest.raises(ValueError, match="rng"):
        renderer.render(np.eye(3), np.array([0, 0, 400.0]))
    with pytest.raises(ValueError, match=r"R \(3, 3\)"):
        renderer.render(np.eye(2), np.zeros(3), np.random.default_rng(0))


# A 200-degree circular fisheye (equidistant Kannala-Brandt: 100 degrees off axis at 480 px).
FISHEYE = Camera("fisheye", 1000, 1000, 275.0, 275.0, 499.5, 499.5, 0, [0.0, 0.0, 0.0, 0.0],
                 model="kannala_brandt")


def facing(off_axis_deg: float, distance_mm: float):
    """cam_from_board (R, t) of BOARD's centre ``off_axis_deg`` from the optical axis (toward
    +x), its printed front facing the camera."""
    a = np.radians(off_axis_deg)
    d = np.array([np.sin(a), 0.0, np.cos(a)])
    x = np.cross([0.0, 1.0, 0.0], d)
    R = np.column_stack([x / np.linalg.norm(x), [0.0, 1.0, 0.0], d])
    return R, distance_mm * d - R[:, :2] @ BOARD.outline_centre_mm


@pytest.mark.parametrize("off_axis_deg", [95.0, 70.0])
def test_a_wide_lens_sees_the_board_where_its_rays_meet_it(off_axis_deg):
    """Past 90 degrees the board is behind the camera's plane: every pixel well inside a square
    (3 mm from its edges, a few pixels here) shows that square's colour as the pixel's own exact
    ray (Camera.rays, float64) meets the board."""
    R, t = facing(off_axis_deg, 300.0)
    image = AnalyticRenderer(FISHEYE, BOARD, RenderSettings()).render(R, t).reshape(-1)
    rays, ok = FISHEYE.rays(FISHEYE.pixel_grid().reshape(-1, 2))
    n = R[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = (n @ t) / (rays @ n)
    board = (lam[:, None] * rays - t) @ R[:, :2]  # board (X, Y) mm of each pixel's ray
    hit = ok & (lam > 0)
    texture = BOARD.texture(10.0) > 128  # white, at 10 texels per mm

    def colour(offset_mm):
        ij = np.floor((board + offset_mm - BOARD.texture_origin_mm) * 10.0)
        ij = np.where(hit[:, None], ij, -1).astype(int)
        on = np.all((ij >= 0) & (ij < texture.shape[::-1]), 1)
        return on, texture[np.where(on, ij[:, 1], 0), np.where(on, ij[:, 0], 0)]

    on, white = colour(0.0)
    inside = on.copy()
    for offset in np.array([[3, 0], [-3, 0], [0, 3], [0, -3], [2, 2], [-2, 2], [2, -2], [-2, -2]]):
        o, w = colour(offset)
        inside &= o & (w == white)
    assert inside.sum() > 5000  # measured 1.1e4 (95 degrees), 8.9e3 (70)
    assert np.array_equal(image[inside] > 128, white[inside])
    # Nothing of the board is drawn elsewhere: pixels whose ray misses it by more than 5 mm
    # (the texture level's blur reaches 3-5 mm where the board is seen at a grazing angle near
    # the image circle) show the background.
    near = np.zeros_like(on)
    for offset in 5 * np.array([[0, 0], [1, 0], [-1, 0], [0, 1], [0, -1], [1, 1], [-1, 1],
                                [1, -1], [-1, -1]]):
        near |= colour(offset)[0]
    assert np.all(image[ok & ~near] == round(RenderSettings().background))


def test_a_turned_view_renders_the_same_image(monkeypatch):
    """A board 70 degrees off axis rendered in the camera's own view and in one turned toward
    it (as one past 75 degrees is) gives the same image to interpolation's rounding."""
    from stereo_bench.render import analytic

    R, t = facing(70.0, 300.0)
    rays = analytic.PixelRays(FISHEYE)
    straight = AnalyticRenderer(FISHEYE, BOARD, RenderSettings(), rays).render(R, t)
    monkeypatch.setattr(analytic, "_TURN_DEG", 30.0)
    turned_view = rays.toward(BOARD.outline_mm() @ R[:, :2].T + t)
    assert turned_view.Q is not None
    turned = AnalyticRenderer(FISHEYE, BOARD, RenderSettings(), rays).render(R, t)
    diff = np.abs(straight.astype(int) - turned)
    assert diff.max() <= 1 and (diff > 0).mean() < 0.01


def test_a_process_keeps_the_rays_of_a_lens_for_every_camera_of_it(monkeypatch):
    """Cameras of one lens (another name, another pose) share the rays a process built for the
    first, and render with them exactly what their own rays give; another lens gets its own,
    and the oldest of more than MAX_KEPT_RAYS lenses is dropped; rays of another lens are
    refused."""
    from stereo_bench.render import analytic

    monkeypatch.setattr(analytic, "_kept_rays", type(analytic._kept_rays)())
    moved = WIDE.with_params(rvec=np.array([0.1, -0.2, 0.05]), tvec=np.array([30.0, 5.0, 0.0]))
    moved = Camera.from_dict({**moved.to_dict(), "name": "other"})
    first = analytic.pixel_rays(WIDE)
    assert analytic.pixel_rays(moved) is first
    R, t = facing(20.0, 400.0)
    shared = AnalyticRenderer(moved, BOARD, RenderSettings()).render(R, t)
    own = AnalyticRenderer(moved, BOARD, RenderSettings(), analytic.PixelRays(moved)).render(R, t)
    assert np.array_equal(shared, own)
    lenses = [Camera.from_dict({**WIDE.to_dict(), "fx": WIDE.fx + k}) for k in range(1, 5)]
    assert all(analytic.pixel_rays(c) is not first for c in lenses)
    assert len(analytic._kept_rays) == analytic.MAX_KEPT_RAYS
    assert analytic.pixel_rays(WIDE) is not first  # the oldest was dropped
    with pytest.raises(ValueError, match="another lens"):
        AnalyticRenderer(lenses[0], BOARD, RenderSettings(), first)
