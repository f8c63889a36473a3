"""Chessboard corners at the saddle point of the intensity (``calib.subpix``).

References:
- analytic X-junctions: an ideal chessboard corner through a known homography, integrated over each pixel (8x8
  samples) and blurred, so the true corner is known exactly;
- a slow, readable re-implementation (one ``np.linalg.lstsq`` per corner on windows sampled by
  ``scipy.ndimage.map_coordinates``), which the vectorised code must equal;
- rendered ChArUco views (``tests.calib_synth``), where OpenCV's own ``CharucoDetector`` corners are the baseline.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.ndimage import map_coordinates

from calib.subpix import _fit_operator, refine_saddle, window_half


def x_junction(centre, angle_deg=20.0, shear=0.25, persp=(0.002, -0.001), blur=1.8, noise=0.0, size=41,
               seed=0) -> np.ndarray:
    """A (size, size) uint8 image of one chessboard corner at ``centre`` (OpenCV pixel convention).

    The board's (x, y) maps to the image by a rotation, a shear and a perspective term about the corner, so its edges
    meet at an angle other than 90 deg and are not symmetric lines through the pixel grid.
    """
    ss = 8
    coords = (np.arange(size * ss) + 0.5) / ss - 0.5  # sample positions in pixel units
    u, v = np.meshgrid(coords, coords)
    a = np.deg2rad(angle_deg)
    A = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]) @ np.array([[1.0, shear], [0.0, 1.0]])
    H = np.eye(3)
    H[:2, :2] = A
    H[2, :2] = persp
    Hinv = np.linalg.inv(H)
    du, dv = u - centre[0], v - centre[1]
    w = Hinv[2, 0] * du + Hinv[2, 1] * dv + Hinv[2, 2]
    x = (Hinv[0, 0] * du + Hinv[0, 1] * dv + Hinv[0, 2]) / w
    y = (Hinv[1, 0] * du + Hinv[1, 1] * dv + Hinv[1, 2]) / w
    fine = np.where(x * y > 0, 225.0, 35.0)
    img = fine.reshape(size, ss, size, ss).mean(axis=(1, 3))
    if blur > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur)
    img = img + np.random.default_rng(seed).normal(0.0, noise, img.shape)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def slow_saddle(gray, point, half, iterations=5):
    """One corner, step by step: weighted quadratic fit by lstsq, move to its stationary point, repeat."""
    ys, xs = np.mgrid[-half:half + 1, -half:half + 1].astype(np.float64)
    sigma = half / 1.5 / np.sqrt(2.0)  # the Gaussian that weights the squared residuals
    weight = np.sqrt(np.exp(-(xs ** 2 + ys ** 2) / (2 * sigma ** 2))).ravel()
    design = np.stack([xs.ravel() ** 2, xs.ravel() * ys.ravel(), ys.ravel() ** 2, xs.ravel(), ys.ravel(),
                       np.ones(xs.size)], 1)
    p = np.asarray(point, np.float64).copy()
    for _ in range(iterations):
        window = map_coordinates(gray.astype(np.float64), [p[1] + ys.ravel(), p[0] + xs.ravel()], order=1)
        # weighted least squares with weights w: minimise sum w (A c - I)^2 -> rows scaled by sqrt(w)
        (a, b, c, d, e, _f), *_ = np.linalg.lstsq(design * weight[:, None], window * weight, rcond=None)
        hessian = np.array([[2 * a, b], [b, 2 * c]])
        p = p + np.linalg.solve(hessian, -np.array([d, e]))
    return p


@pytest.mark.parametrize("centre, angle, shear, blur", [
    ((20.0, 20.0), 0.0, 0.0, 1.0),
    ((20.37, 19.81), 20.0, 0.25, 1.8),
    ((19.62, 20.45), -35.0, -0.3, 2.5),
    ((20.5, 20.5), 50.0, 0.1, 0.7),
])
def test_the_saddle_of_a_blurred_x_junction_is_its_corner(centre, angle, shear, blur):
    """Without noise the fit lands within 0.01 px of the true corner, from a start 1.5 px away: what is left is the
    pixel integration and the perspective term, which break the half-turn symmetry only slightly. OpenCV's
    ``cornerSubPix`` on the same image is the baseline, and on blurred corners ours must be no less accurate."""
    img = x_junction(centre, angle, shear, blur=blur)
    start = np.array([[centre[0] + 1.1, centre[1] - 1.0]])
    refined, found = refine_saddle(img, start, 4)
    assert found[0]
    err = np.linalg.norm(refined[0] - centre)
    assert err < 0.01, err
    cv = start.astype(np.float32).reshape(-1, 1, 2).copy()
    cv2.cornerSubPix(img, cv, (5, 5), (-1, -1), (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4))
    assert err <= np.linalg.norm(cv.reshape(2) - centre) + 1e-3


def test_noisy_corners_scatter_as_little_as_the_window_allows():
    """With 3 grey levels of noise on a 190-level step, 1.8 px blur: the corners of 40 noise draws scatter by less than
    0.05 px RMS (the renders in BENCHMARKS.md show 0.03), and noise adds no bias: their mean lies within 0.01 px
    (2 standard errors of the mean) of the noise-free fit. That fit is itself 0.02 px off: this corner's
    perspective term breaks the half-turn symmetry a little."""
    centre = np.array([20.3, 20.6])
    clean, _ = refine_saddle(x_junction(centre, 15.0, 0.2, blur=1.8), centre[None] + 0.7, 4)
    assert np.linalg.norm(clean[0] - centre) < 0.025
    corners = []
    for seed in range(40):
        img = x_junction(centre, 15.0, 0.2, blur=1.8, noise=3.0, seed=seed)
        refined, found = refine_saddle(img, centre[None] + 0.7, 4)
        assert found[0]
        corners.append(refined[0])
    err = np.array(corners) - centre
    assert np.sqrt((err ** 2).sum(1).mean()) < 0.05
    assert np.linalg.norm(np.array(corners).mean(0) - clean[0]) < 0.01


def test_the_vectorised_fit_equals_the_slow_one():
    img = x_junction((20.37, 19.81), 20.0, 0.25, blur=1.8, noise=2.0)
    starts = np.array([[21.0, 19.0], [19.6, 20.4], [20.2, 20.1]])
    fast, found = refine_saddle(img, starts, 4, tolerance_px=0.0)
    assert found.all()
    for s, f in zip(starts, fast):
        np.testing.assert_allclose(f, slow_saddle(img, s, 4), atol=1e-6)


def test_the_operator_is_the_weighted_least_squares_fit():
    """The precomputed operator returns the exact coefficients of a quadratic surface."""
    half = 3
    ys, xs = np.mgrid[-half:half + 1, -half:half + 1].astype(np.float64)
    coef = np.array([0.7, -1.3, 0.2, 4.0, -2.5, 100.0])
    surface = coef[0] * xs ** 2 + coef[1] * xs * ys + coef[2] * ys ** 2 + coef[3] * xs + coef[4] * ys + coef[5]
    op, design = _fit_operator(half)
    np.testing.assert_allclose(op @ surface.ravel(), coef, atol=1e-9)
    np.testing.assert_allclose(design @ coef, surface.ravel(), atol=1e-9)


def test_windows_without_a_corner_keep_their_points():
    """Flat grey, a straight edge, a blob (a maximum, no saddle) and a window over the image's border: the points
    stay where they were and are reported as not found."""
    flat = np.full((41, 41), 128, np.uint8)
    edge = np.where(np.arange(41)[None, :] < 20.3, 35, 225).repeat(41, 0).astype(np.uint8)
    edge = cv2.GaussianBlur(edge, (0, 0), 1.5)
    yy, xx = np.mgrid[0:41, 0:41]
    blob = (35 + 190 * np.exp(-((xx - 20.2) ** 2 + (yy - 19.7) ** 2) / 20.0)).astype(np.uint8)
    for img in (flat, edge, blob):
        pts = np.array([[20.4, 19.6]])
        refined, found = refine_saddle(img, pts, 4)
        assert not found[0]
        np.testing.assert_array_equal(refined, pts)
    corner = x_junction((2.5, 20.0))
    refined, found = refine_saddle(corner, np.array([[2.8, 20.2]]), 4)
    assert not found[0] and np.allclose(refined, [[2.8, 20.2]])


def test_window_half_follows_the_square_size():
    np.testing.assert_array_equal(window_half(np.array([0.0, 10.0, 20.0, 26.0, 40.0, 400.0])), [2, 2, 3, 4, 4, 4])


def test_bad_shapes_are_refused():
    img = x_junction((20.0, 20.0))
    with pytest.raises(ValueError, match=r"\(n, 2\)"):
        refine_saddle(img, np.zeros((3, 3)), 4)
    with pytest.raises(ValueError, match="2D image"):
        refine_saddle(np.zeros((4, 4, 3), np.uint8), np.zeros((1, 2)), 4)


def test_board_corners_are_several_times_closer_to_the_truth_than_opencvs():
    """Blurred renders of a strongly distorted ChArUco board (1.8 px blur, 3 grey levels of noise, seeds the settings
    were not chosen on): ``BoardDetector``'s corners against OpenCV's ``CharucoDetector`` with its defaults on the same
    images, both against the renderer's true projections (``cv2.projectPoints``). Measured: 0.03-0.05 px RMS against
    0.13-0.16 (BENCHMARKS.md); the test asks for half of OpenCV's error, and at least as many corners."""
    from benchmarks.bench_calib import CONDITIONS, K, LENSES, SIZE, SPEC
    from calib.board import parse_board
    from calib.detect import BoardDetector
    from tests.calib_synth import Renderer, operator_poses

    board = parse_board(SPEC)
    renderer = Renderer(board, K, LENSES["strong"], SIZE, supersample=4, px_per_mm=12.0)
    ours, theirs = BoardDetector(board), cv2.aruco.CharucoDetector(BoardDetector(board).cv_board)
    err_ours, err_theirs = [], []
    rng = np.random.default_rng(5)
    for pose in operator_poses(board, K, SIZE, 6, seed=5):
        img = renderer.render(pose, rng=rng, **CONDITIONS["blur"])
        truth = renderer.project(pose)
        det, _ = ours.detect(img)
        corners, ids, _, _ = theirs.detectBoard(img)
        if ids is None:
            assert det is None or len(det.ids) >= 6
            continue
        ids = ids.ravel()
        err_theirs.append(np.linalg.norm(corners.reshape(-1, 2) - truth[ids], axis=1))
        assert det is not None and len(det.ids) >= len(ids) - 1
        err_ours.append(np.linalg.norm(det.image_points - truth[det.ids], axis=1))
    rms = [np.sqrt(np.mean(np.concatenate(e) ** 2)) for e in (err_ours, err_theirs)]
    assert len(err_theirs) >= 4
    assert rms[0] < 0.5 * rms[1], rms
