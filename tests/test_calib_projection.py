"""calib.projection against OpenCV (cv2.projectPoints / cv2.undistortPoints) and float64 gradcheck."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from calib.camera import Camera, default_camera
from calib.projection import camera_tensors, project_points, undistort_points

K_REF = np.array([[812.5, 0.0, 641.2], [0.0, 809.1, 355.7], [0.0, 0.0, 1.0]])


def random_dist(rng: np.random.Generator, n: int) -> np.ndarray:
    """Realistic-magnitude coefficients: barrel/pincushion of a few %, small tangential/prism/tilt."""
    d = np.zeros(n)
    if n == 0:
        return d
    d[:2] = rng.uniform(-0.3, 0.3, 2) * (1.0, 0.3)
    d[2:4] = rng.uniform(-2e-3, 2e-3, 2)
    if n >= 5:
        d[4] = rng.uniform(-0.05, 0.05)
    if n >= 8:
        d[5:8] = rng.uniform(-0.1, 0.1, 3) * (1.0, 0.3, 0.1)
    if n >= 12:
        d[8:12] = rng.uniform(-2e-3, 2e-3, 4)
    if n >= 14:
        d[12:14] = rng.uniform(-0.01, 0.01, 2)  # sensor tilt, radians
    return d


def random_scene(rng, frames: int, n: int):
    """Board-like points (mm) seen from random rotations/translations in front of the camera."""
    obj = np.column_stack([rng.uniform(-150, 150, (n, 2)), rng.uniform(-40, 40, n)])
    rvecs = rng.normal(0, 0.35, (frames, 3))
    tvecs = np.column_stack([rng.uniform(-60, 60, (frames, 2)), rng.uniform(450, 900, frames)])
    cam = np.stack([obj @ cv2.Rodrigues(r)[0].T + t for r, t in zip(rvecs, tvecs)])
    return obj, rvecs, tvecs, cam


def assert_close(actual: torch.Tensor, expected: np.ndarray, atol: float) -> None:
    assert tuple(actual.shape) == expected.shape, (tuple(actual.shape), expected.shape)  # shapes first
    err = np.abs(actual.detach().cpu().numpy() - expected).max()
    assert err <= atol, f"max abs difference {err:.3g} > {atol}"


@pytest.mark.parametrize("n_dist", [0, 4, 5, 8, 12, 14])
def test_project_matches_cv2_project_points(n_dist):
    rng = np.random.default_rng(n_dist)
    obj, rvecs, tvecs, cam = random_scene(rng, frames=4, n=300)
    dist = random_dist(rng, n_dist)
    expected = np.stack([
        cv2.projectPoints(obj, r, t, K_REF, dist if n_dist else None)[0].reshape(-1, 2)
        for r, t in zip(rvecs, tvecs)
    ])
    out = project_points(torch.from_numpy(cam), torch.from_numpy(K_REF), torch.from_numpy(dist))
    # float64 on both sides: agreement is limited by rounding (~1e-10 px); 1e-4 px is the spec,
    # far below detector noise (~0.05 px) yet 1000x above any formula mismatch (a wrong sign of a
    # tangential term moves points by >0.01 px here).
    assert_close(out, expected, 1e-4)


def test_project_batched_per_frame_intrinsics():
    rng = np.random.default_rng(7)
    _obj, _r, _t, cam = random_scene(rng, frames=3, n=50)
    Ks = np.stack([K_REF * s for s in (1.0, 0.8, 1.3)])
    Ks[:, 2, 2] = 1.0
    dists = np.stack([random_dist(rng, 5) for _ in range(3)])
    out = project_points(torch.from_numpy(cam), torch.from_numpy(Ks), torch.from_numpy(dists))
    expected = np.stack([
        cv2.projectPoints(cam[f], np.zeros(3), np.zeros(3), Ks[f], dists[f])[0].reshape(-1, 2) for f in range(3)
    ])
    assert_close(out, expected, 1e-4)
    # a single camera broadcasts over (windows, frames)
    out2 = project_points(torch.from_numpy(cam).expand(2, 3, 50, 3), torch.from_numpy(Ks[0]),
                          torch.from_numpy(dists[0]))
    assert out2.shape == (2, 3, 50, 2)
    assert_close(out2[1, 2], cv2.projectPoints(cam[2], np.zeros(3), np.zeros(3), Ks[0], dists[0])[0].reshape(-1, 2), 1e-4)


def test_project_follows_dtype_and_float32_accuracy():
    rng = np.random.default_rng(3)
    _o, _r, _t, cam = random_scene(rng, 2, 100)
    dist = random_dist(rng, 5)
    K, d = camera_tensors(Camera(K_REF, dist, (1280, 720)), torch.float32)
    out = project_points(torch.from_numpy(cam).float(), K, d)
    assert out.dtype == torch.float32
    expected = np.stack([cv2.projectPoints(c, np.zeros(3), np.zeros(3), K_REF, dist)[0].reshape(-1, 2) for c in cam])
    # float32 has a 24-bit mantissa: at ~1000 px the spacing is 6e-5 px; a few ulps of error
    # accumulate through the polynomial, so 2e-3 px.
    assert_close(out, expected, 2e-3)


def test_project_gradcheck_float64():
    rng = np.random.default_rng(11)
    _o, _r, _t, cam = random_scene(rng, 2, 6)
    pts = torch.from_numpy(cam).requires_grad_(True)
    K = torch.from_numpy(K_REF.copy()).requires_grad_(True)
    dist = torch.from_numpy(random_dist(rng, 8)).requires_grad_(True)
    assert torch.autograd.gradcheck(project_points, (pts, K, dist), eps=1e-6, atol=1e-5)
    und_in = project_points(pts, K, dist).detach().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda p, k, d: undistort_points(p, k, d), (und_in, K, dist), eps=1e-6, atol=1e-5)


@pytest.mark.parametrize("n_dist", [4, 5, 8])
def test_undistort_inverts_projection_and_matches_cv2(n_dist):
    rng = np.random.default_rng(20 + n_dist)
    _o, _r, _t, cam = random_scene(rng, 2, 200)
    dist = random_dist(rng, n_dist)
    Kt, dt = torch.from_numpy(K_REF), torch.from_numpy(dist)
    distorted = project_points(torch.from_numpy(cam), Kt, dt)
    undistorted = undistort_points(distorted, Kt, dt)
    ideal = project_points(torch.from_numpy(cam), Kt, None)
    # the fixed-point iteration (20 steps) converges to ~1e-9 px for these lens magnitudes
    assert_close(undistorted, ideal.numpy(), 1e-5)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
    ref = cv2.undistortPointsIter(distorted[0].numpy().reshape(-1, 1, 2), K_REF, dist, np.eye(3), K_REF, crit)
    assert_close(undistorted[0], ref.reshape(-1, 2), 1e-5)


def test_no_distortion_paths_agree():
    rng = np.random.default_rng(5)
    _o, _r, _t, cam = random_scene(rng, 1, 30)
    pts, K = torch.from_numpy(cam), torch.from_numpy(K_REF)
    a = project_points(pts, K, None)
    b = project_points(pts, K, torch.zeros(0, dtype=torch.float64))
    c = project_points(pts, K, torch.zeros(5, dtype=torch.float64))
    expected = cam[..., :2] / cam[..., 2:] * (K_REF[0, 0], K_REF[1, 1]) + K_REF[:2, 2]
    for out in (a, b, c):
        assert_close(out, expected, 1e-9)
    assert torch.equal(undistort_points(a, K, None), a)


@pytest.mark.parametrize(
    "points_shape, K_shape, dist_shape, message",
    [
        ((10, 2), (3, 3), (5,), r"points must have shape \(\*, N, 3\), got \(10, 2\)"),
        ((3,), (3, 3), (5,), r"points must have shape"),
        ((10, 3), (3, 4), (5,), r"K must have shape \(\*, 3, 3\), got \(3, 4\)"),
        ((10, 3), (3, 3), (6,), r"dist must have shape \(\*, D\) with D in"),
        ((4, 10, 3), (3, 3, 3), (5,), r"batch dimensions do not broadcast: points .* \(4, 10, 3\), K .* \(3, 3, 3\)"),
        ((4, 10, 3), (4, 3, 3), (2, 5), r"batch dimensions do not broadcast.*dist .* \(2, 5\)"),
    ],
)
def test_project_rejects_bad_shapes(points_shape, K_shape, dist_shape, message):
    with pytest.raises(ValueError, match=message):
        project_points(torch.ones(points_shape), torch.ones(K_shape), torch.zeros(dist_shape))


def test_project_rejects_mixed_dtype():
    with pytest.raises(ValueError, match="float64 .* but points are torch.float32"):
        project_points(torch.ones(5, 3), torch.eye(3, dtype=torch.float64), None)


def test_camera_tensors_round_trip_default_camera():
    cam = default_camera(1920, 1080)
    K, d = camera_tensors(cam, torch.float64)
    centre = project_points(torch.tensor([[0.0, 0.0, 1000.0]], dtype=torch.float64), K, d)
    # the optical axis hits the exact image centre ((w-1)/2, (h-1)/2) under the pixel-centre rule
    assert torch.allclose(centre, torch.tensor([[959.5, 539.5]], dtype=torch.float64))
