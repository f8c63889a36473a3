"""The global blendshape baseline (GBS, Lewis et al. 2014; the AIM paper's Table 2 baseline).

Per frame, fit ``X ~ R (N + sum_k w_k D_k) + t`` to a registered mesh ``X`` (V, 3) by alternating
a rigid pose (Kabsch: :meth:`scipy.spatial.transform.Rotation.align_vectors`) with a linear least
squares solve of the weights on the fixed pose (:func:`scipy.optimize.lsq_linear`, bounded to
``[0, 1]`` by default, or unbounded), reduced exactly to a K x K system through the Cholesky
factor of the normal matrix. Every vertex counts equally (dense constraints, as in the
paper's 3D fitting experiment). Units are whatever the inputs use (mm here).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import lsq_linear
from scipy.spatial.transform import Rotation


@dataclass
class GBSFit:
    weights: np.ndarray     # (K,)
    R: np.ndarray           # (3, 3)
    t: np.ndarray           # (3,)
    vertices: np.ndarray    # (V, 3) the fitted mesh R (N + w @ D) + t
    iterations: int


def rigid_fit(source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``R, t`` minimising ``sum |R source + t - target|^2`` (both (V, 3))."""
    cs, ct = source.mean(0), target.mean(0)
    rot, _ = Rotation.align_vectors(target - ct, source - cs)
    R = rot.as_matrix()
    return R, ct - R @ cs


def fit_gbs(target: np.ndarray, neutral: np.ndarray, deltas: np.ndarray, bounded: bool = True,
            w0: np.ndarray | None = None, max_iterations: int = 50, tol: float = 1e-5) -> GBSFit:
    """Fit the blendshape model ``(neutral (V, 3), deltas (K, V, 3))`` to ``target (V, 3)``.

    Alternates the rigid pose for the current shape with the weights for the current pose until
    the weights change by less than ``tol`` (max abs). ``w0`` warm-starts the weights (e.g. the
    previous frame's). Every step lowers the same squared error, so the loop converges monotonically.
    """
    target, neutral = np.asarray(target, np.float64), np.asarray(neutral, np.float64)
    deltas = np.asarray(deltas, np.float64)
    if target.shape != neutral.shape or deltas.shape[1:] != neutral.shape:
        raise ValueError(f"shapes differ: target {target.shape}, neutral {neutral.shape}, deltas {deltas.shape}")
    K = len(deltas)
    B = deltas.reshape(K, -1)                                          # (K, 3V)
    # |B^T w - y|^2 = |L^T w - L^-1 B y|^2 + const with B B^T = L L^T: the same solution on a K x K system
    L = np.linalg.cholesky(B @ B.T)
    w = np.zeros(K) if w0 is None else np.asarray(w0, np.float64).copy()
    it = 0
    for it in range(1, max_iterations + 1):
        shape = neutral + np.tensordot(w, deltas, axes=1)
        R, t = rigid_fit(shape, target)
        y = ((target - t) @ R - neutral).ravel()                       # R^T (X - t) - N, in the model frame
        rhs = np.linalg.solve(L, B @ y)
        w_new = (lsq_linear(L.T, rhs, bounds=(0.0, 1.0), method="bvls").x if bounded
                 else np.linalg.solve(L.T, rhs))
        done = np.abs(w_new - w).max() < tol
        w = w_new
        if done:
            break
    shape = neutral + np.tensordot(w, deltas, axes=1)
    R, t = rigid_fit(shape, target)
    return GBSFit(w, R, t, shape @ R.T + t, it)


def fit_gbs_sequence(meshes: np.ndarray, neutral: np.ndarray, deltas: np.ndarray, bounded: bool = True,
                     **kw) -> list[GBSFit]:
    """:func:`fit_gbs` per frame of ``meshes (T, V, 3)``, each warm-started from the previous frame."""
    fits, w = [], None
    for X in meshes:
        f = fit_gbs(X, neutral, deltas, bounded=bounded, w0=w, **kw)
        fits.append(f)
        w = f.weights
    return fits
