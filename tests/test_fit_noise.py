"""The noise-adaptive smoothing's two pieces (models.fit_noise): the noise read from residuals, and the scale."""

from __future__ import annotations

import numpy as np
import pytest

from models.fit_noise import face_px_per_mm, residual_noise_px, temporal_prior_scale


def test_residual_noise_is_the_gaussian_sigma_robust_to_outliers_and_skips_unused_landmarks():
    """1.3 px Gaussian residuals on 30 x 400 landmarks with 5 % of them 40 px off (landmarks the actor cannot
    explain): the estimate stays within 8 % of 1.3 (5 % of outliers move the median of |r| to the 0.5 / 0.95
    quantile of the inliers', +6 %; its standard error here is ~1 %), where the RMS is ~7x too large. Unused
    landmarks (weight 0, NaN) do not count, whatever their residual."""
    rng = np.random.default_rng(0)
    J, L = 30, 400
    fit = rng.uniform(0, 640, (J, L, 2))
    points = fit + rng.normal(0.0, 1.3, (J, L, 2))
    wild = rng.random((J, L)) < 0.05
    points[wild] += 40.0
    weights = np.ones((J, L))
    weights[:, :50] = 0.0
    points[:, :50] += 500.0                 # unused: would dominate if counted
    points[3, 60] = np.nan                  # missing
    sigma, per_frame = residual_noise_px(points, weights, fit)
    assert sigma == pytest.approx(1.3, rel=0.08)
    r = (fit - points)[:, 50:][np.isfinite(points[:, 50:]).all(-1)]
    assert np.sqrt(np.mean(r ** 2)) > 5 * sigma
    assert per_frame == pytest.approx(L - 50 - 1 / J)


def test_landmarks_per_frame_counts_confidence_and_only_frames_with_a_face():
    fit = np.zeros((3, 4, 2))
    points = fit + 1.0
    weights = np.array([[1.0, 0.5, 0.5, 0.0], [0.0, 0.0, 0.0, 0.0], [1.0, 1.0, 1.0, 1.0]])
    sigma, per_frame = residual_noise_px(points, weights, fit)
    assert sigma == pytest.approx(1.4826) and per_frame == pytest.approx((2.0 + 4.0) / 2)
    assert residual_noise_px(points, np.zeros((3, 4)), fit) == (pytest.approx(np.nan, nan_ok=True), 0.0)
    with pytest.raises(ValueError, match="expected points2d"):
        residual_noise_px(points, weights[:, :3], fit)


def test_face_px_per_mm_is_the_image_scale_of_a_flat_face_and_skips_unused_landmarks():
    """A flat face (template z = 0) seen face-on at 1.7 px per mm in frame 0 and 0.8 in frames 1-2: the median
    frame's scale; an unused landmark far off and a frame with 2 landmarks do not count."""
    rng = np.random.default_rng(1)
    X = np.c_[rng.normal(0.0, 40.0, (50, 2)), np.zeros(50)]
    pts = np.stack([300 + 1.7 * X[:, :2], 100 + 0.8 * X[:, :2], 50 + 0.8 * X[:, :2], 0.8 * X[:, :2]])
    w = np.ones((4, 50))
    w[2, 7] = 0.0
    pts[2, 7] = 1e4
    w[3, 2:] = 0.0
    assert face_px_per_mm(pts, w, X) == pytest.approx(0.8)
    assert face_px_per_mm(pts[:1], w[:1], X) == pytest.approx(1.7)
    assert np.isnan(face_px_per_mm(pts[3:], w[3:], X))


@pytest.mark.parametrize("sigma, landmarks, expected", [
    (0.53, 800.0, 1.0),            # the tuning conditions: the prior as tuned
    (0.30, 2000.0, 1.0),           # better than tuned: never weaker
    (1.59, 800.0, 3.0),            # 3x the noise
    (0.53, 200.0, 4.0),            # a quarter of the landmarks
    (1.59, 200.0, 12.0),
    (5.0, 50.0, 30.0),             # capped
    (float("nan"), 0.0, 1.0),      # no landmark used: unknown noise, the prior as tuned
])
def test_temporal_prior_scale(sigma, landmarks, expected):
    assert temporal_prior_scale(sigma, landmarks, 0.53, 800.0, 30.0) == pytest.approx(expected)
    # the face at the tuning's size in the image, or its size unknown: the same
    assert temporal_prior_scale(sigma, landmarks, 0.53, 800.0, 30.0, 1.65, 1.65) == pytest.approx(expected)
    assert temporal_prior_scale(sigma, landmarks, 0.53, 800.0, 30.0, float("nan"), 1.65) == pytest.approx(expected)


def test_a_smaller_face_in_the_image_scales_by_the_square_of_its_size():
    """Half the tuning's px per mm: the same noise in px is a 2x weaker constraint per mm of motion, and the
    2D term (px^2 near its minimum) already weighs 4x less against the prior: k / 4, at least 1."""
    assert temporal_prior_scale(1.59, 200.0, 0.53, 800.0, 30.0, 0.825, 1.65) == pytest.approx(3.0)
    assert temporal_prior_scale(0.53, 200.0, 0.53, 800.0, 30.0, 0.825, 1.65) == pytest.approx(1.0)
    # a larger face than the tuning's: as at the tuning's size (measured there; larger ones were not)
    assert temporal_prior_scale(1.59, 800.0, 0.53, 800.0, 30.0, 3.3, 1.65) == pytest.approx(3.0)
