"""Noise-adaptive smoothing of 2D fits: the landmarks' noise, read from a solved window's residuals, sets how
strongly the expression coefficients are held together over frames.

The coefficients' temporal prior (``FitSettings.coeff_temporal_weight``) was tuned where the landmarks are
good: about 800 of them per frame with 0.5 px of noise, on a face of 1.65 px per mm (1280x720, the face 75 %
of the height). The 2D term of the energy is a mean over the landmarks, so it weighs the same whatever their
number and noise, while what a frame's landmarks say about its expression falls with fewer or noisier
landmarks. A detector with 300 landmarks and 1.5 px of noise then leaves the prior ~10x too weak, and the
expressions follow the noise.

:func:`temporal_prior_scale` multiplies the prior by ``k = (sigma / ref_px) * (ref_landmarks / L)``, times
``(s / ref_s)^2`` for a face smaller in the image than at the tuning (``s`` px per mm,
:func:`face_px_per_mm`), clamped to ``[1, max]``: never weaker than tuned. Linear in ``sigma``, not squared:
above ``robust_px`` the pseudo-Huber loss already weighs a residual by ``~1 / |r|``. The face-size factor is
empirical: at 360x288 the noise rule alone smoothed a talking take too much (0.331 against 0.314 mm with 300
landmarks at 0.5 px), with it that take is as before; a face larger than at the tuning is taken as at the
tuning. Measured (BENCHMARKS.md, "2D fit out of the actor's span", "Noise-adaptive smoothing"): on the demo
actor's synthetic takes (talk, turns, calm: blinks, syllables at 4 Hz) and held-out ICT performances, never
worse than the fixed prior by more than 0.005 mm and up to 13 % better at 300 landmarks and 1.5 px. Where an
actor's coefficients move much faster than the demo actor's (the 3-shape test actor, a 12-degree jaw at
4 Hz) the fixed prior is better (+2 % at 0.5 px, +12 % at 3 px on a 320x240 take).

:func:`residual_noise_px` estimates ``sigma`` and ``L`` from a solved window: the median absolute residual
(x and y of every landmark used) times 1.4826, which is the standard deviation of Gaussian noise and is
robust to the landmarks the actor cannot explain (on the held-out performances it reads 0.52-0.53 px for
0.5 px of noise, 1.47-1.50 for 1.5 px, whether the prior is 1x or 10x). Pure numpy; no torch.
"""

from __future__ import annotations

import numpy as np

#: 1 / Phi^-1(3/4): median |x| times this is the standard deviation of a normal distribution
MAD_TO_SIGMA = 1.4826


def residual_noise_px(points2d: np.ndarray, weights: np.ndarray, landmarks_fit: np.ndarray) -> tuple[float, float]:
    """``(sigma px, landmarks per frame)`` of a solved window.

    Args:
        points2d: ``(J, L, 2)`` px, the landmarks fitted (NaN where missing).
        weights: ``(J, L)`` their confidences (0 = not used).
        landmarks_fit: ``(J, L, 2)`` px, the fit's projection of the same landmarks.

    ``sigma`` is ``MAD_TO_SIGMA`` times the median of ``|fit - landmark|`` over both axes of every landmark used
    (weight > 0, finite); landmarks per frame is the mean over the frames that use any of the sum of their
    weights. ``(nan, 0.0)`` when no landmark is used.
    """
    p, w, f = np.asarray(points2d, np.float64), np.asarray(weights, np.float64), np.asarray(landmarks_fit, np.float64)
    if p.shape != f.shape or p.shape[:2] != w.shape or p.shape[-1:] != (2,):
        raise ValueError(f"expected points2d and landmarks_fit (J, L, 2) and weights (J, L); got {p.shape}, "
                         f"{f.shape} and {w.shape}")
    used = (w > 0) & np.isfinite(p).all(-1) & np.isfinite(f).all(-1)
    if not used.any():
        return float("nan"), 0.0
    sigma = MAD_TO_SIGMA * float(np.median(np.abs(f[used] - p[used])))
    frames = used.any(1)
    per_frame = float(np.where(used, w, 0.0)[frames].sum(1).mean())
    return sigma, per_frame


def face_px_per_mm(points2d: np.ndarray, weights: np.ndarray, template_points: np.ndarray) -> float:
    """How large the face is in the image: the median over frames of the RMS distance of the landmarks used from
    their centroid (px) over that of their template points (mm, 3D). ``points2d (J, L, 2)``, ``weights (J, L)``,
    ``template_points (L, 3)``; nan when no frame uses 3 landmarks."""
    p, w, X = np.asarray(points2d, np.float64), np.asarray(weights, np.float64), np.asarray(template_points, np.float64)
    used = (w > 0) & np.isfinite(p).all(-1)                                   # (J, L)
    n = used.sum(1)
    ok = n >= 3
    if not ok.any():
        return float("nan")
    u = used[ok].astype(np.float64)                                           # (J', L)
    n = n[ok].astype(np.float64)
    pz = np.where(used[ok][..., None], p[ok], 0.0)                            # (J', L, 2)
    # RMS spread about the centroid: mean |a|^2 - |mean a|^2, over the landmarks used
    spread_px = np.einsum("jlc,jlc->j", pz, pz) / n - np.square(pz.sum(1) / n[:, None]).sum(1)
    spread_mm = u @ np.square(X).sum(1) / n - np.square(u @ X / n[:, None]).sum(1)
    return float(np.median(np.sqrt(np.maximum(spread_px, 0.0) / np.maximum(spread_mm, 1e-12))))


def temporal_prior_scale(sigma_px: float, landmarks: float, ref_px: float, ref_landmarks: float,
                         max_scale: float, px_per_mm: float = float("nan"), ref_px_per_mm: float = 0.0) -> float:
    """``k`` in ``[1, max_scale]`` that multiplies the coefficients' temporal prior (see the module docstring):
    ``(sigma_px / ref_px) * (ref_landmarks / landmarks) * min(1, (px_per_mm / ref_px_per_mm)^2)``, the last
    factor only when both are known and positive; 1 when the noise is unknown (no landmark used)."""
    if not (np.isfinite(sigma_px) and landmarks > 0 and ref_px > 0):
        return 1.0
    k = (sigma_px / ref_px) * (ref_landmarks / landmarks)
    if ref_px_per_mm > 0 and np.isfinite(px_per_mm) and px_per_mm > 0:
        k *= min(1.0, (px_per_mm / ref_px_per_mm) ** 2)
    return float(min(max(k, 1.0), max_scale))
