"""Sub-pixel position of chessboard corners as the saddle point of the image intensity.

At an inner chessboard corner two dark and two light squares meet. Whatever the blur, as long as the lens's point
spread is centrally symmetric, the image around the corner is symmetric under a half turn about it, and the corner is
the saddle point of the intensity. Fitting a quadratic surface ``a x^2 + b x y + c y^2 + d x + e y + f`` to a small
Gaussian-weighted window and moving to its stationary point finds it, as in Lucchese & Mitra (2002) and in the
sub-pixel steps of ROCHADE (Placht et al. 2014) and libcbdetect (Geiger et al. 2012).

Why not OpenCV's ``cornerSubPix``: ``CharucoDetector`` refines its corners with it (Förstner's gradient orthogonality).
On our renders (``benchmarks/bench_calib.py``'s lenses and framings) its corners are 0.06-0.16 px RMS from the true
projections, up to 2 px off on blurred, strongly distorted views; the saddle fit from the same starts is 0.02-0.05
px RMS (``BENCHMARKS.md``, "Corners from the saddle of the intensity").

The window's half size must stay inside the symmetric part of the pattern: on a ChArUco board the markers' black
borders sit in both light squares at the same offsets, so they keep the symmetry, but the markers' bits do not. A half
size of 4 px (a 9x9 window whose squared residuals are weighted by a Gaussian of std 1.9 px) suits squares of 25 px
and more; smaller squares get smaller windows (:func:`window_half`). Larger windows (a fifth or a quarter of the
square) were measured and are less accurate.

Pure numpy on one grayscale image; no file I/O.
"""

from __future__ import annotations

import numpy as np

#: the largest window half size (px) and its share of the square's side in the image
MAX_HALF = 4
HALF_PER_SQUARE = 0.15
#: a window holds a corner when its saddle's strength, sqrt(b^2 - 4 a c), is this many standard errors of ``b`` (from
#: the fit's residuals, at least 0.5 grey levels): real corners score 7-36 (from 5 % contrast and 5 px blur up), flat
#: noise about 1, an edge 0
MIN_SADDLE_T = 4.0


def window_half(square_px: np.ndarray) -> np.ndarray:
    """Window half size (int px, 2..``MAX_HALF``) for corners whose squares measure ``square_px`` (n,) in the image."""
    square_px = np.asarray(square_px, np.float64)
    return np.clip(np.round(HALF_PER_SQUARE * square_px), 2, MAX_HALF).astype(int)


def _fit_operator(half: int) -> tuple[np.ndarray, np.ndarray]:
    """The weighted least squares fit on a (2 half + 1)^2 window: ``(operator (6, m), design (m, 6))``; the operator
    takes window intensities (row-major, y then x) to (a, b, c, d, e, f), the design takes those back to intensities."""
    ys, xs = np.mgrid[-half:half + 1, -half:half + 1].astype(np.float64)
    x, y = xs.ravel(), ys.ravel()
    # squared residuals weighted by a Gaussian of std half / (1.5 sqrt 2): 1.9 px for the 9x9 window
    sqrt_weight = np.exp(-(x * x + y * y) / (2.0 * (half / 1.5) ** 2))
    A = np.stack([x * x, x * y, y * y, x, y, np.ones_like(x)], 1)
    return np.linalg.pinv(A * sqrt_weight[:, None]) * sqrt_weight[None, :], A


def _windows(image: np.ndarray, centres: np.ndarray, half: int) -> np.ndarray:
    """(n, (2 half + 1)^2) bilinear samples of ``image`` (float) on a pixel grid centred at each of ``centres`` (n, 2).

    Exact bilinear weights: ``cv2.remap`` quantises positions to 1/32 px, which is as large as the accuracy sought.
    The caller keeps every window inside the image.
    """
    offsets = np.arange(-half, half + 1, dtype=np.float64)
    x = centres[:, 0, None, None] + offsets[None, None, :]
    y = centres[:, 1, None, None] + offsets[None, :, None]
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = x - x0, y - y0
    x0, y0 = x0.astype(int), y0.astype(int)
    x1 = np.minimum(x0 + 1, image.shape[1] - 1)
    y1 = np.minimum(y0 + 1, image.shape[0] - 1)
    top = image[y0, x0] * (1.0 - fx) + image[y0, x1] * fx
    bottom = image[y1, x0] * (1.0 - fx) + image[y1, x1] * fx
    return (top * (1.0 - fy) + bottom * fy).reshape(len(centres), -1)


def window_inside(points: np.ndarray, half, image_shape) -> np.ndarray:
    """(n,) bool: the (2 half + 1)^2 window about each of ``points`` (n, 2) lies inside an image of ``image_shape``."""
    points = np.asarray(points, np.float64)
    half = np.asarray(half, np.float64)
    h_img, w_img = image_shape[:2]
    return ((points[:, 0] - half >= 0) & (points[:, 0] + half <= w_img - 1)
            & (points[:, 1] - half >= 0) & (points[:, 1] + half <= h_img - 1))


def refine_saddle(gray: np.ndarray, points: np.ndarray, half, iterations: int = 5,
                  tolerance_px: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
    """Move chessboard corners to the saddle point of the intensity around them.

    ``gray`` (H, W) uint8 or float image; ``points`` (n, 2) pixels (OpenCV convention: pixel centres at integers);
    ``half`` the window half size, an int or (n,) ints. Returns ``(refined (n, 2) float64, found (n,) bool)``. A
    corner keeps its input position (``found`` False) where the fit is no clear saddle (the window holds no corner:
    see ``MIN_SADDLE_T``), where it would leave its window, or where the window does not lie inside the image.
    """
    points = np.asarray(points, np.float64)
    if points.ndim != 2 or points.shape[1] != 2:
        raise ValueError(f"points must be (n, 2), got {points.shape}")
    if gray.ndim != 2:
        raise ValueError(f"gray must be a 2D image, got {gray.shape}")
    n = len(points)
    halves = np.broadcast_to(np.asarray(half, int), (n,))
    image = np.asarray(gray, np.float64)
    out = points.copy()
    found = np.zeros(n, bool)
    for half_size in np.unique(halves):
        idx = np.flatnonzero(halves == half_size)
        op, design = _fit_operator(int(half_size))
        b_gain = float(np.linalg.norm(op[1]))  # standard error of b per grey level of pixel noise
        start = points[idx]
        cur = start.copy()
        alive = np.ones(len(idx), bool)
        for _ in range(iterations):
            alive &= window_inside(cur, half_size, image.shape)
            if not alive.any():
                break
            windows = _windows(image, cur[alive], int(half_size))
            coef = op @ windows.T
            a, b, c, d, e, _f = coef
            noise = np.maximum((windows - (design @ coef).T).std(axis=1), 0.5)
            det = 4.0 * a * c - b * b
            saddle = np.sqrt(np.maximum(-det, 0.0)) >= MIN_SADDLE_T * noise * b_gain
            safe = np.where(saddle, det, -1.0)
            step = np.stack([(b * e - 2.0 * c * d) / safe, (b * d - 2.0 * a * e) / safe], 1)
            rows = np.flatnonzero(alive)
            cur[rows[saddle]] += step[saddle]
            alive[rows[~saddle]] = False
            far = np.linalg.norm(cur - start, axis=1) > half_size
            alive &= ~far
            if np.all(np.linalg.norm(step[saddle], axis=1) < tolerance_px):
                break
        out[idx[alive]] = cur[alive]
        found[idx[alive]] = True
    return out, found
