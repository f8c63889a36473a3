"""Initial rigid head poses for a take: per-frame PnP on the landmarks, gaps interpolated, smoothed.

Convention (as everywhere in the project): a head-frame (template-frame) point ``x`` maps to the
camera frame by ``R @ x + t`` (column vectors, mm; OpenCV camera axes x right, y down, z forward).
This is exactly OpenCV's ``rvec, tvec`` of :func:`cv2.solvePnP`, so no conversion is needed.

The 3D model of the PnP is the actor's *neutral* at the landmarks' template points; expressions and
the jaw are left to the sequence fit (its ``F_T`` corrects these poses).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass

import cv2
import numpy as np

from models.quaternion import gaussian_smooth, matrix_from_quat, quat_from_matrix, slerp_keys


@dataclass(frozen=True)
class PnPSettings:
    """How the initial poses are found (saved with the resolved fit settings)."""

    min_weight_fraction: float = 0.5
    """Points whose confidence is below this fraction of the frame's largest are not used."""
    min_points: int = 6
    ransac_px: float = 6.0
    """RANSAC inlier threshold in pixels (wild detections are rejected before the LM refinement)."""
    smooth_sigma_frames: float = 1.0
    """Gaussian smoothing of the per-frame poses over time (0 = off)."""
    track_keep: float = 0.9
    """Tracking (:class:`PnPChain`): a frame starts from the previous frame's pose and is refined from it
    alone, without RANSAC, while that pose's inliers (``ransac_px``) are at least this fraction of the
    previous frame's; below it (a cut, a fast turn, a lost face) RANSAC searches afresh. 0 = RANSAC on
    every frame."""

    def to_dict(self) -> dict:
        return asdict(self)


def _pnp_inputs(model_points: np.ndarray, points2d: np.ndarray, weights: np.ndarray, K: np.ndarray, dist: np.ndarray,
                settings: PnPSettings) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """The PnP's ``(object (N, 3), image (N, 2), K, dist)`` in float64, the points finite and confident
    enough; None when too few."""
    ok = np.isfinite(points2d).all(1) & np.isfinite(weights) & (weights > 0)
    if ok.sum() < settings.min_points:
        return None
    ok &= weights >= settings.min_weight_fraction * weights[ok].max()
    if ok.sum() < settings.min_points:
        return None
    return (np.ascontiguousarray(model_points[ok], dtype=np.float64),
            np.ascontiguousarray(points2d[ok], dtype=np.float64), np.asarray(K, np.float64),
            np.asarray(dist, np.float64))


def pnp_frame(model_points: np.ndarray, points2d: np.ndarray, weights: np.ndarray, K: np.ndarray,
              dist: np.ndarray, settings: PnPSettings = PnPSettings(),
              guess: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray] | None:
    """Head pose of one frame by RANSAC: ``(R (3,3), t (3,))`` or None when too few usable points.

    Args:
        model_points: ``(L, 3)`` head-frame points (mm); points2d ``(L, 2)`` px (NaN = missing);
        weights ``(L,)`` confidence; K ``(3, 3)``; dist OpenCV coefficients; guess ``(rvec, tvec)``.
    """
    pts = _pnp_inputs(model_points, points2d, weights, K, dist, settings)
    if pts is None:
        return None
    obj, img, K, dist = pts
    use_guess = guess is not None
    rvec0 = guess[0].copy() if use_guess else None
    tvec0 = guess[1].copy() if use_guess else None
    found, rvec, tvec, inliers = cv2.solvePnPRansac(
        obj, img, K, dist, rvec0, tvec0, useExtrinsicGuess=use_guess, iterationsCount=100,
        reprojectionError=settings.ransac_px, confidence=0.999, flags=cv2.SOLVEPNP_EPNP if not use_guess
        else cv2.SOLVEPNP_ITERATIVE)
    if not found or inliers is None or len(inliers) < settings.min_points:
        return None
    idx = inliers[:, 0]
    rvec, tvec = cv2.solvePnPRefineLM(obj[idx], img[idx], K, dist, rvec, tvec)
    R = cv2.Rodrigues(rvec)[0]
    t = tvec.reshape(3)
    if t[2] <= 0:  # the face is in front of the camera
        return None
    return R, t


def _inliers(obj: np.ndarray, img: np.ndarray, rvec, tvec, K, dist, px: float) -> np.ndarray:
    """``(N,)`` bool: the points the pose ``(rvec, tvec)`` projects within ``px`` of their image point."""
    uv = cv2.projectPoints(obj, rvec, tvec, K, dist)[0][:, 0]
    return np.square(uv - img).sum(1) < px * px


def track_frame(model_points: np.ndarray, points2d: np.ndarray, weights: np.ndarray, K: np.ndarray,
                dist: np.ndarray, settings: PnPSettings, guess: tuple[np.ndarray, np.ndarray], min_inliers: float
                ) -> tuple[np.ndarray, np.ndarray, int] | None:
    """Head pose of one frame refined from the previous frame's ``guess (rvec, tvec)`` alone (no RANSAC):
    Levenberg-Marquardt from the guess on the points it explains within ``ransac_px``. ``(R, t, inliers of
    the result)``, or None when fewer than ``min_inliers`` (or ``min_points``) are explained by the guess or
    by the result (the caller then runs :func:`pnp_frame`). The gate is RANSAC's: a wider one lets in the
    points an expression moves away from the neutral model, and the poses get worse (measured on a
    synthetic take of the demo actor: 0.24 deg mean error with this gate, 0.34 with 1.5x, 0.43 with 2x,
    0.29 for RANSAC on every frame)."""
    pts = _pnp_inputs(model_points, points2d, weights, K, dist, settings)
    if pts is None:
        return None
    obj, img, K, dist = pts
    need = max(settings.min_points, min_inliers)
    near = _inliers(obj, img, guess[0], guess[1], K, dist, settings.ransac_px)
    if near.sum() < need:
        return None
    rvec, tvec = cv2.solvePnPRefineLM(obj[near], img[near], K, dist, guess[0].copy(), guess[1].copy())
    inl = _inliers(obj, img, rvec, tvec, K, dist, settings.ransac_px)
    if inl.sum() < need:
        return None
    t = tvec.reshape(3)
    if t[2] <= 0:
        return None
    return cv2.Rodrigues(rvec)[0], t, int(inl.sum())


def clean_row(points, weights, found, n_landmarks: int, frame: int) -> tuple[np.ndarray, np.ndarray]:
    """One frame's ``(points (L, 2) float64, weights (L,))`` as the fit uses them: a point that is not finite,
    or of a frame without a face, weighs 0; weights are clipped at 0 (None: 1 where finite)."""
    p = np.asarray(points, np.float64)
    if p.shape != (n_landmarks, 2):
        raise ValueError(f"frame {frame}: landmarks should be ({n_landmarks}, 2); got {p.shape}")
    finite = np.isfinite(p).all(1)
    w = finite.astype(np.float64) if weights is None else np.asarray(weights, np.float64).copy()
    if w.shape != (n_landmarks,):
        raise ValueError(f"frame {frame}: weights should be ({n_landmarks},); got {w.shape}")
    return p, np.where(finite & bool(found) & np.isfinite(w), np.clip(w, 0.0, None), 0.0)


class PnPChain:
    """The per-frame PnP of a take, in frame order: each frame starts from the previous good pose (and
    from nothing when that fails). ``next(points, weights)`` -> ``(R, t)`` or None (too few points).

    Tracking (``settings.track_keep``): while the previous pose still explains most of the points, the
    frame is refined from it (:func:`track_frame`, a fraction of RANSAC's cost when the landmarks are
    noisy or partly wrong); otherwise RANSAC (:func:`pnp_frame`) from the previous pose, then from nothing.

    :func:`initial_head_poses` runs it over a take, :class:`capture.fit.stream.StreamLandmarkSource` on the
    rows it reads, unless they bring its result (the fit process's parent runs it beside detection,
    :mod:`capture.fit.process`): the same calls in the same order give the same poses.
    """

    def __init__(self, model_points: np.ndarray, K: np.ndarray, dist: np.ndarray, settings: PnPSettings):
        self.model, self.K, self.dist, self.settings = model_points, K, dist, settings
        self.guess = None
        self.inliers = 0            # the previous pose's inliers
        self.seconds = 0.0
        self.tracked = 0            # frames refined from the previous pose without RANSAC

    def next(self, p: np.ndarray, w: np.ndarray):
        t0 = time.perf_counter()
        res = None
        s = self.settings
        if self.guess is not None and s.track_keep > 0:
            tr = track_frame(self.model, p, w, self.K, self.dist, s, self.guess, s.track_keep * self.inliers)
            if tr is not None:
                res, self.inliers = tr[:2], tr[2]
                self.tracked += 1
        if res is None:
            res = pnp_frame(self.model, p, w, self.K, self.dist, s, self.guess)
            if res is None and self.guess is not None:  # a bad guess must not lose the frame
                res = pnp_frame(self.model, p, w, self.K, self.dist, s, None)
            if res is not None and s.track_keep > 0:
                obj, img, K, dist = _pnp_inputs(self.model, p, w, self.K, self.dist, s)
                self.inliers = int(_inliers(obj, img, cv2.Rodrigues(res[0])[0], res[1], K, dist, s.ransac_px).sum())
        if res is not None:
            self.guess = (cv2.Rodrigues(res[0])[0], res[1].reshape(3, 1).copy())
        self.seconds += time.perf_counter() - t0
        return res


def interpolate_poses(R: np.ndarray, t: np.ndarray, ok: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fill frames where ``ok`` is False: slerp / linear between neighbours, held at the ends.

    Args: R ``(T, 3, 3)``, t ``(T, 3)``, ok ``(T,)`` bool with at least one True.
    """
    T = len(ok)
    good = np.flatnonzero(ok)
    if len(good) == 0:
        raise ValueError("no frame has a head pose to interpolate from")
    frames = np.arange(T)
    clipped = np.clip(frames, good[0], good[-1])
    t_out = np.stack([np.interp(clipped, good, t[good, k]) for k in range(3)], 1)
    if len(good) == 1:
        R_out = np.broadcast_to(R[good[0]], (T, 3, 3)).copy()
    else:
        R_out = slerp_keys(good, R[good], clipped)
    return R_out, t_out


def smooth_poses(R: np.ndarray, t: np.ndarray, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """Gaussian smoothing over time of rotations (sign-aligned quaternions) and translations."""
    if sigma <= 0 or len(t) < 2:
        return R, t
    q = quat_from_matrix(R)
    for j in range(1, len(q)):  # one hemisphere, so that averaging neighbours is meaningful
        if np.dot(q[j], q[j - 1]) < 0:
            q[j] = -q[j]
    return matrix_from_quat(gaussian_smooth(q, sigma)), gaussian_smooth(t, sigma)


def initial_head_poses(model_points: np.ndarray, points2d: np.ndarray, weights: np.ndarray, K: np.ndarray,
                       dist: np.ndarray, settings: PnPSettings = PnPSettings()
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-frame PnP, interpolated over failures, smoothed: ``(R (T,3,3), t (T,3), found (T,) bool)``.

    Args:
        model_points: ``(L, 3)`` the actor's neutral at the landmarks' template points (mm).
        points2d: ``(T, L, 2)`` px, NaN where missing; weights ``(T, L)`` (0 for frames without a face).
    Raises ValueError when no frame has enough landmarks.
    """
    T, L = points2d.shape[:2]
    if model_points.shape != (L, 3) or weights.shape != (T, L):
        raise ValueError(f"expected model_points ({L}, 3) and weights ({T}, {L}) for points2d {points2d.shape}; "
                         f"got {model_points.shape} and {weights.shape}")
    R = np.tile(np.eye(3), (T, 1, 1))
    t = np.zeros((T, 3))
    found = np.zeros(T, bool)
    chain = PnPChain(model_points, K, dist, settings)
    for j in range(T):
        res = chain.next(points2d[j], weights[j])
        if res is not None:
            R[j], t[j] = res
            found[j] = True
    if not found.any():
        raise ValueError("no frame has enough landmarks for a head pose (PnP failed everywhere)")
    R, t = interpolate_poses(R, t, found)
    R, t = smooth_poses(R, t, settings.smooth_sigma_frames)
    return R, t, found


def rigid_align(src: np.ndarray, dst: np.ndarray,
                weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rigid ``(R, t)`` with ``R @ src + t ~ dst`` (Kabsch); ``src, dst (N, 3)``, optional
    ``weights (N,)`` >= 0 on the squared residuals."""
    if weights is None:
        ms, md = src.mean(0), dst.mean(0)
        H = (src - ms).T @ (dst - md)
    else:
        w = np.asarray(weights, np.float64)
        ms, md = w @ src / w.sum(), w @ dst / w.sum()
        H = ((src - ms) * w[:, None]).T @ (dst - md)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    return R, md - R @ ms
