"""The analytic renderer's sampling: board texels looked up through a plane's homography,
the joint time and pixel-area samples of an exposure, interpolation weights, the board's cells
in the image, and the renderer's Gaussian noise (its integer path compiled with numba).
"""

from __future__ import annotations

import math
import sys

import cv2
import numba
import numpy as np
from scipy.special import ndtri

OUTSIDE = -1.0e4  # texel coordinate far outside every texture


def noise_draws(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    """The sensor noise's draws (shape) uint16 from ``rng``: draw d is the standard normal
    value ``NORMAL_QUANTILES[d]`` (inverse-CDF sampling of 16-bit uniforms, 3x faster than
    ``standard_normal``: the 65536 equiprobable quantiles of N(0, 1), rescaled to unit
    variance; tails are cut at 4.3 sigma, probability 1.5e-5).

    The draws are ``rng.integers(0, 1 << 16, shape, uint16)``'s. numpy takes those 16 bits at a
    time from 32-bit words, low half first, and PCG64 its 32-bit words from 64-bit outputs, low
    half first: so, on a little-endian machine, when the generator holds no half-used word and
    the count is a multiple of four, they are its raw 64-bit outputs read as uint16 (6 ms on a
    12 MP frame against 13; tests/render/test_imaging.py checks both ways agree and leave the
    generator alike). Otherwise they are drawn as integers."""
    n = math.prod(shape)
    bits = rng.bit_generator
    if n % 4 == 0 and sys.byteorder == "little" and type(bits) is np.random.PCG64 \
            and not bits.state["has_uint32"]:
        return bits.random_raw(n // 4).view(np.uint16).reshape(shape)
    return rng.integers(0, 1 << 16, size=shape, dtype=np.uint16)


def noisy_levels(rng: np.random.Generator, canvas: np.ndarray, sigma: float) -> np.ndarray:
    """The 8-bit image of ``canvas`` (H, W) uint16 in 1/256 grey levels plus Gaussian noise of
    ``sigma`` levels (:func:`noise_draws`): the same values as
    ``cv2.addWeighted(canvas, 1 / 256, NORMAL_QUANTILES[draws], sigma, 0, dtype=cv2.CV_8U)``
    (float32 arithmetic, rounded half to even, saturated), in one compiled pass without the
    float noise image: 10 ms on a 12 MP frame against 41 ms."""
    draws = noise_draws(rng, canvas.shape)
    return _noisy_levels(canvas, draws, NORMAL_QUANTILES, np.float32(sigma))


@numba.njit(cache=True, nogil=True)
def _noisy_levels(canvas, draws, quantiles, sigma):
    out = np.empty(canvas.shape, np.uint8)
    scale = np.float32(1 / 256)
    noise = np.empty(canvas.shape[1], np.float32)
    for i in range(canvas.shape[0]):
        # The row's noise gathered first: the arithmetic that follows then compiles to vector
        # instructions (10 ms on a 12 MP frame against 19 with the gather in the same loop).
        for j in range(canvas.shape[1]):
            noise[j] = quantiles[draws[i, j]] * sigma
        for j in range(canvas.shape[1]):
            level = np.rint(np.float32(canvas[i, j]) * scale + noise[j])
            out[i, j] = np.uint8(min(max(level, np.float32(0)), np.float32(255)))
    return out


def _normal_quantiles() -> np.ndarray:
    q = ndtri((np.arange(1 << 16) + 0.5) / (1 << 16))
    return (q / np.sqrt(np.mean(q * q))).astype(np.float32)


NORMAL_QUANTILES = _normal_quantiles()


def cells_touching(nodes: np.ndarray, n_cells: tuple[int, int]) -> np.ndarray:
    """(rows, cols) uint8 cells with a flagged corner; node (a, b) is cell (a, b)'s top-left."""
    cells = np.zeros(n_cells, dtype=np.uint8)
    for da in (0, 1):
        for db in (0, 1):
            sub = nodes[da:da + n_cells[0], db:db + n_cells[1]]
            cells[:sub.shape[0], :sub.shape[1]] |= sub
    return cells


def inverse_2x2(J: np.ndarray) -> np.ndarray:
    """Inverses of 2x2 matrices (N, 2, 2)."""
    det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
    inv = np.stack([J[:, 1, 1], -J[:, 0, 1], -J[:, 1, 0], J[:, 0, 0]], -1) / det[:, None]
    return inv.reshape(-1, 2, 2)


def grid_interpolation(values: np.ndarray, rows: np.ndarray, cols: np.ndarray, h: int, w: int
                       ) -> np.ndarray:
    """``values`` (a, b, C) float32 given at the increasing integer ``rows`` (a,) and ``cols``
    (b,) (first 0, last h - 1 and w - 1), linearly interpolated at every pixel (h, w, C):
    first along the rows, then along the columns, each output from its two nodes in float32,
    in one compiled pass (numpy's take and arithmetic, one axis after the other, took 5.7 ms
    where this takes 2.5 on a 258 x 3000 band)."""
    return _grid_interpolation(np.ascontiguousarray(values, np.float32), *_brackets(rows, h),
                               *_brackets(cols, w))


def _brackets(nodes: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """For 0..n-1: the index of the node at or before each (the last interval's for n - 1)
    and the float32 fraction of the way to the next node."""
    i = np.arange(n)
    k = np.clip(np.searchsorted(nodes, i, side="right") - 1, 0, len(nodes) - 2)
    return k, ((i - nodes[k]) / (nodes[k + 1] - nodes[k])).astype(np.float32)


@numba.njit(cache=True, nogil=True)
def _grid_interpolation(values, kr, fr, kc, fc):
    b, C = values.shape[1], values.shape[2]
    h, w = len(kr), len(kc)
    rows = np.empty((h, b, C), np.float32)
    for i in range(h):
        k, f = kr[i], fr[i]
        for j in range(b):
            for c in range(C):
                rows[i, j, c] = values[k, j, c] + (values[k + 1, j, c] - values[k, j, c]) * f
    out = np.empty((h, w, C), np.float32)
    for i in range(h):
        for j in range(w):
            k, f = kc[j], fc[j]
            for c in range(C):
                out[i, j, c] = rows[i, k, c] + (rows[i, k + 1, c] - rows[i, k, c]) * f
    return out


def plane_texels(M: np.ndarray):
    """``to_texels`` of a plane homography M (3, 3) (see ``sample_texels``)."""
    def plane(xy, cut):
        texels = cv2.perspectiveTransform(xy, M)
        if cut:
            texels[xy @ M[2, :2] + M[2, 2] <= 0] = OUTSIDE
        return texels
    return plane


def sample_texels(xy: np.ndarray, to_texels, s: int, exact: bool) -> np.ndarray:
    """Texel coordinates (s h, s w, 2) float32 of the s x s samples of h x w pixels.

    ``xy`` (h + 2, w + 2, 2): normalized coordinates of the pixels and a one-pixel margin;
    ``to_texels(xy, cut)``: normalized -> texel coordinates (``AnalyticRenderer._texel_map``).
    cv2.resize's half-pixel convention puts sample j of the upsampled grid at pixel
    (j + 0.5) / s - 0.5, exactly the sample offsets, so interpolating and cropping the margin
    gives the samples. Normally the smooth texel map is interpolated (one mapping per pixel);
    ``exact`` interpolates the rays (smooth everywhere) and maps each sample, cutting out
    samples whose ray meets the board behind the camera.
    """
    h, w = xy.shape[0] - 2, xy.shape[1] - 2
    size = (s * (w + 2), s * (h + 2))
    if not exact:
        up = cv2.resize(to_texels(xy, False), size, interpolation=cv2.INTER_LINEAR)
        return up[s:-s, s:-s]
    up = cv2.resize(xy, size, interpolation=cv2.INTER_LINEAR)[s:-s, s:-s]
    return to_texels(up, True)


def offset_texels(xy: np.ndarray, to_texels, offsets: np.ndarray, exact: bool) -> list:
    """Texel coordinates [(h, w, 2) float32] of one sample per pixel of h x w pixels for each
    of ``offsets`` (n, 2): (du, dv) px from the pixel's centre, |du|, |dv| < 1.

    Arguments as in :func:`sample_texels`, of which these are samples of a finer grid: the
    same bilinear interpolation of the pixel-centre texel map (or of the rays, ``exact``).
    """
    if not exact:
        texels = to_texels(xy, False)
        return [_shifted(texels, offset) for offset in offsets]
    return [to_texels(_shifted(xy, offset), True) for offset in offsets]


def _shifted(grid: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """(h, w, C) bilinear interpolation of ``grid`` (h + 2, w + 2, C), a one-pixel margin
    around h x w pixels, at each pixel's centre plus ``offset`` (du, dv), |du|, |dv| < 1."""
    du, dv = float(offset[0]), float(offset[1])
    near = grid[1:-1]
    far = grid[2:] if dv >= 0 else grid[:-2]
    rows = cv2.addWeighted(near, 1.0 - abs(dv), far, abs(dv), 0.0)
    near = rows[:, 1:-1]
    far = rows[:, 2:] if du >= 0 else rows[:, :-2]
    return cv2.addWeighted(near, 1.0 - abs(du), far, abs(du), 0.0)


def time_area_offsets(k: int, s: int) -> np.ndarray:
    """(k, s, 2) pixel-area offsets (du, dv) px of an exposure's k sub-frames, s per sub-frame:
    sub-frame i samples the cells (a, (a + i) mod s), a = 0..s-1, of the s x s grid of
    :func:`sample_texels` (offsets (a + 0.5) / s - 0.5).

    Every sub-frame samples each column and each row of the grid once (an N-rooks set), so its
    samples are balanced in u and in v (their mean is the pixel's centre: no shift, and an edge
    parallel to either axis sees the pixel's full extent at every instant); s consecutive
    sub-frames cover the whole grid, and consecutive sub-frames use different diagonals, so
    time and pixel area are integrated together at s samples per pixel and sub-frame instead
    of s^2.
    """
    grid = (np.arange(s) + 0.5) / s - 0.5
    a = np.arange(s)
    b = (a[None, :] + np.arange(k)[:, None]) % s
    return np.stack([np.broadcast_to(grid[a], b.shape), grid[b]], -1)
