"""Rotations as unit quaternions, in numpy: what the fit's start needs (PnP poses interpolated over gaps and
smoothed over frames, the actor's jaw rotations as rotation vectors) without importing scipy, whose
``spatial.transform`` and ``ndimage`` cost the fit process 0.3-0.4 s before its first window.

Quaternions are ``(..., 4)`` float64 ``(x, y, z, w)``, scalar last, as scipy's ``Rotation.as_quat``;
rotation matrices ``(..., 3, 3)`` act on column vectors. Each function equals its scipy counterpart to
float64 rounding on rotation matrices (``tests/test_quaternion.py``).
"""

from __future__ import annotations

import numpy as np

__all__ = ["gaussian_smooth", "matrix_from_quat", "quat_from_matrix", "rotvec_from_matrix", "slerp_keys"]


def quat_from_matrix(R: np.ndarray) -> np.ndarray:
    """``(..., 4)`` unit quaternions (w >= 0) of rotation matrices ``(..., 3, 3)`` (Shepperd's method: the
    largest of the four squared components is taken from the diagonal, the others from the off-diagonal)."""
    R = np.asarray(R, np.float64)
    m00, m11, m22 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    tr = m00 + m11 + m22
    # 4 q_k^2 for k = x, y, z, w
    cand = np.stack([1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22, 1 + tr], -1)
    k = np.argmax(cand, -1)
    s = np.sqrt(np.maximum(np.take_along_axis(cand, k[..., None], -1)[..., 0], 1e-300))   # 2 |q_k|
    d21, d02, d10 = R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]
    s01, s02, s12 = R[..., 0, 1] + R[..., 1, 0], R[..., 0, 2] + R[..., 2, 0], R[..., 1, 2] + R[..., 2, 1]
    q = np.stack([
        np.select([k == 0, k == 1, k == 2], [s * s, s01, s02], d21),
        np.select([k == 0, k == 1, k == 2], [s01, s * s, s12], d02),
        np.select([k == 0, k == 1, k == 2], [s02, s12, s * s], d10),
        np.select([k == 0, k == 1, k == 2], [d21, d02, d10], s * s)], -1) / (2 * s[..., None])
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., 3:] < 0, -q, q)


def matrix_from_quat(q: np.ndarray) -> np.ndarray:
    """``(..., 3, 3)`` rotation matrices of quaternions ``(..., 4)`` (normalised first)."""
    q = np.asarray(q, np.float64)
    x, y, z, w = np.moveaxis(q / np.linalg.norm(q, axis=-1, keepdims=True), -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1)], -2)


def rotvec_from_matrix(R: np.ndarray) -> np.ndarray:
    """``(..., 3)`` rotation vectors (axis times angle in [0, pi], rad) of rotation matrices ``(..., 3, 3)``."""
    q = quat_from_matrix(R)
    v, w = q[..., :3], q[..., 3]
    n = np.linalg.norm(v, axis=-1)
    angle = 2 * np.arctan2(n, w)
    # angle / n -> 2 / w as n -> 0 (w -> 1)
    scale = np.where(n > 1e-12, angle / np.where(n > 1e-12, n, 1.0), 2.0 / np.where(w > 0, w, 1.0))
    return v * scale[..., None]


def slerp_keys(times: np.ndarray, keys: np.ndarray, at: np.ndarray) -> np.ndarray:
    """Rotations ``(N, 3, 3)`` at times ``at (N,)`` within ``[times[0], times[-1]]``, each interpolated
    along the shortest arc between the two key rotations ``keys (K, 3, 3)`` at increasing ``times (K,)``
    around it (scipy's ``Slerp``)."""
    times = np.asarray(times, np.float64)
    q = quat_from_matrix(keys)
    at = np.asarray(at, np.float64)
    i = np.clip(np.searchsorted(times, at, side="right") - 1, 0, len(times) - 2)
    t = ((at - times[i]) / (times[i + 1] - times[i]))[:, None]
    q0, q1 = q[i], q[i + 1]
    dot = (q0 * q1).sum(-1, keepdims=True)
    q1 = np.where(dot < 0, -q1, q1)            # the shortest arc
    dot = np.abs(dot).clip(max=1.0)
    theta = np.arccos(dot)
    sin = np.sin(theta)
    near = sin < 1e-9
    a = np.where(near, 1 - t, np.sin((1 - t) * theta) / np.where(near, 1.0, sin))
    b = np.where(near, t, np.sin(t * theta) / np.where(near, 1.0, sin))
    return matrix_from_quat(a * q0 + b * q1)


def gaussian_smooth(x: np.ndarray, sigma: float, truncate: float = 4.0) -> np.ndarray:
    """``x (T, ...)`` smoothed along its first axis by a normalised Gaussian of ``sigma`` samples, the
    edges extended with the end values (scipy's ``ndimage.gaussian_filter1d(..., mode="nearest")``)."""
    x = np.asarray(x, np.float64)
    r = int(truncate * sigma + 0.5)
    k = np.exp(-0.5 * (np.arange(-r, r + 1) / sigma) ** 2)
    k /= k.sum()
    pad = np.concatenate([np.repeat(x[:1], r, 0), x, np.repeat(x[-1:], r, 0)], 0)
    out = np.zeros_like(x)
    for j, kj in enumerate(k):
        out += kj * pad[j:j + len(x)]
    return out
