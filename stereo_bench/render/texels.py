"""The analytic renderer's sampling: board texels looked up through a plane's homography,
interpolation weights, the board's cells in the image, and the renderer's Gaussian noise.
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy.special import ndtri

OUTSIDE = -1.0e4  # texel coordinate far outside every texture


def gaussian_noise(rng: np.random.Generator, shape: tuple[int, int]) -> np.ndarray:
    """Standard normal noise (shape) float32 from ``rng``, 3x faster than ``standard_normal``.

    Inverse-CDF sampling of 16-bit uniforms: the 65536 equiprobable quantiles of N(0, 1),
    rescaled to unit variance; tails are cut at 4.3 sigma (probability 1.5e-5).
    """
    return _NORMAL_QUANTILES[rng.integers(0, 1 << 16, size=shape, dtype=np.uint16)]


def _normal_quantiles() -> np.ndarray:
    q = ndtri((np.arange(1 << 16) + 0.5) / (1 << 16))
    return (q / np.sqrt(np.mean(q * q))).astype(np.float32)


_NORMAL_QUANTILES = _normal_quantiles()


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


def linear_weights(n: int, nodes: np.ndarray) -> np.ndarray:
    """(n, len(nodes)) float32 weights of linear interpolation at 0..n-1 from values at the
    increasing integer positions ``nodes`` (first 0, last n - 1)."""
    i = np.arange(n)
    k = np.clip(np.searchsorted(nodes, i, side="right") - 1, 0, len(nodes) - 2)
    frac = (i - nodes[k]) / (nodes[k + 1] - nodes[k])
    W = np.zeros((n, len(nodes)), dtype=np.float32)
    W[i, k] = 1 - frac
    W[i, k + 1] = frac
    return W


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
