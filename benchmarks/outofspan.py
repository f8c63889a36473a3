"""Out-of-span 2D takes: held-out ICT performances seen through a camera, and the baselines fitted to them.

Pure data and baselines (no AIM fit here; see ``bench_outofspan.py``):

* :func:`landmark_take`: a held-out performance (:mod:`benchmarks.heldout`, template frame, mm) placed
  in front of the default 1280x720 camera exactly as ``capture synth`` frames a take
  (:func:`capture.synth.scene.head_transforms` at rest; the performance carries its own head motion),
  its landmarks (``capture synth``'s farthest-point set on the template) projected, those facing away
  from the camera dropped (NaN, weight 0), Gaussian noise of ``noise_px`` per axis: independent per
  frame (``noise="iid"``), or as a detector errs (``noise="detector"``): a bias per landmark that stays
  for the whole take (the detector's landmark is not quite the mesh point) plus an error that changes
  slowly over the frames (AR(1), correlation 0.8 from one frame to the next: consecutive frames look
  alike to the network), each of std ``noise_px`` per axis.
* :func:`fit_blendshapes_2d`: the plain baseline an animator would use: per frame a rigid head pose
  and blendshape weights (bounded to [0, 1] by default) on the SAME landmarks, by
  :func:`scipy.optimize.least_squares` (trust region reflective, analytic Jacobian), warm-started from
  the previous frame. With the actor's 19 training shapes it is the baseline; with all 53 ICT shapes
  (the truth's own span) it is the bound of what the landmarks can tell.

Conventions: camera frame OpenCV (x right, y down, z forward), mm; pixels with centres at integers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

#: Regions of the face for per-region errors: ICT vertex ranges are not labelled, so regions are boxes in
#: the template frame (mm) relative to the nose tip: mouth (lips, jaw front), eyes, brows.
FACING_MIN_COS = 0.1
NOISE_MODELS = ("iid", "detector")
DETECTOR_NOISE_CORRELATION = 0.8   # AR(1) correlation of a landmark's error between consecutive frames


@dataclass
class LandmarkTake:
    """A 2D take of a known mesh sequence."""

    points2d: np.ndarray          # (T, L, 2) px, noisy, NaN where the landmark faces away
    weights: np.ndarray           # (T, L) 1 seen, 0 not
    template_points: np.ndarray   # (L, 3) mm, the landmarks on the template
    face_index: np.ndarray        # (L,) triangle of each landmark
    barycentric: np.ndarray       # (L, 3)
    camera: object                # calib.camera.Camera
    truth: np.ndarray             # (T, V, 3) mm, camera frame
    truth_landmarks: np.ndarray   # (T, L, 3) mm, camera frame


def place_in_camera(vertices_head: np.ndarray, template_vertices: np.ndarray, camera) -> tuple[np.ndarray, np.ndarray]:
    """The rest head transform of ``capture synth`` (``x_cam = R x + t``): frontal, centred, 75 % of the height."""
    from capture.synth.scene import head_transforms

    R, t = head_transforms(camera, template_vertices, [0.0], [0.0], [0.0], np.zeros((1, 3)))
    return R[0], t[0]


def landmark_noise(rng: np.random.Generator, T: int, L: int, noise_px: float, model: str = "iid") -> np.ndarray:
    """``(T, L, 2)`` px of landmark error (the module docstring's ``noise`` models)."""
    if model == "iid":
        return rng.normal(0.0, noise_px, (T, L, 2))
    if model != "detector":
        raise ValueError(f"noise model {model!r}: use one of {', '.join(NOISE_MODELS)}")
    rho = DETECTOR_NOISE_CORRELATION
    bias = rng.normal(0.0, noise_px, (L, 2))
    innovations = rng.normal(0.0, noise_px * np.sqrt(1.0 - rho * rho), (T, L, 2))
    first = rng.normal(0.0, noise_px, (L, 2))            # stationary from the first frame
    return bias + ar1(first, innovations)


def ar1(first: np.ndarray, innovations: np.ndarray, rho: float = DETECTOR_NOISE_CORRELATION) -> np.ndarray:
    """``(T, ...)`` the AR(1) series ``x_0 = first``, ``x_j = rho x_{j-1} + innovations_j`` (``innovations[0]`` unused)."""
    out = np.empty_like(innovations)
    out[0] = first
    for j in range(1, len(out)):
        out[j] = rho * out[j - 1] + innovations[j]
    return out


def landmark_take(vertices_head: np.ndarray, template, landmarks: int, noise_px: float, seed: int,
                  size: tuple[int, int] = (1280, 720), noise: str = "iid") -> LandmarkTake:
    """Project ``vertices_head (T, V, 3)`` (template frame, mm) as a take (see the module docstring)."""
    from calib.camera import default_camera
    from capture.synth.detector_onnx import sample_landmarks
    from capture.synth.scene import project

    camera = default_camera(*size)
    tv = np.asarray(template.vertices, np.float64)
    tf = np.asarray(template.faces, np.int64)
    R, t = place_in_camera(vertices_head, tv, camera)
    verts = np.einsum("ij,tvj->tvi", R, np.asarray(vertices_head, np.float64)) + t
    lms = sample_landmarks(template, landmarks, seed=0)
    tri = verts[:, tf[lms.face_index]]                                       # (T, L, 3, 3)
    p3 = np.einsum("lk,tlkc->tlc", lms.barycentric, tri)
    n = np.cross(tri[:, :, 1] - tri[:, :, 0], tri[:, :, 2] - tri[:, :, 0])
    n /= np.linalg.norm(n, axis=-1, keepdims=True).clip(1e-12)
    ray = -p3 / np.linalg.norm(p3, axis=-1, keepdims=True)
    seen = np.einsum("tlc,tlc->tl", n, ray) > FACING_MIN_COS
    rng = np.random.default_rng(seed)
    p2 = project(camera, p3) + landmark_noise(rng, p3.shape[0], p3.shape[1], noise_px, noise)
    p2[~seen] = np.nan
    tp = np.einsum("lk,lkc->lc", lms.barycentric, tv[tf[lms.face_index]])
    return LandmarkTake(p2, seen.astype(np.float64), tp, lms.face_index, lms.barycentric, camera,
                        verts.astype(np.float32), p3)


def at_landmarks(field: np.ndarray, face_index: np.ndarray, barycentric: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """A per-vertex ``field (..., V, 3)`` interpolated at the landmarks -> ``(..., L, 3)``."""
    return np.einsum("lk,...lkc->...lc", barycentric, field[..., np.asarray(faces)[face_index], :])


@dataclass
class BlendshapeFit2D:
    weights: np.ndarray      # (T, K)
    R: np.ndarray            # (T, 3, 3) template -> camera
    t: np.ndarray            # (T, 3) mm
    vertices: np.ndarray     # (T, V, 3) mm, camera frame


def fit_blendshapes_2d(take: LandmarkTake, neutral: np.ndarray, deltas: np.ndarray, faces: np.ndarray,
                       bounded: bool = True, R0: np.ndarray | None = None, t0: np.ndarray | None = None
                       ) -> BlendshapeFit2D:
    """Per frame ``min sum_l |pi(R (N_l + w @ D_l) + t) - p_l|^2`` over ``R, t, w`` (``w`` in [0, 1] if bounded).

    Args:
        take: the landmarks (NaN / weight 0 where unseen) and the camera (no distortion assumed).
        neutral: ``(V, 3)`` mm and deltas ``(K, V, 3)`` mm in the template frame, template topology.
        faces: ``(F, 3)`` the template's triangles (landmarks are barycentric on them).
        R0, t0: the first frame's starting pose (default: ``capture synth``'s rest placement).
    """
    K_cam = np.asarray(take.camera.K, np.float64)
    fx, fy, cx, cy = K_cam[0, 0], K_cam[1, 1], K_cam[0, 2], K_cam[1, 2]
    N = at_landmarks(np.asarray(neutral, np.float64), take.face_index, take.barycentric, faces)       # (L, 3)
    D = at_landmarks(np.asarray(deltas, np.float64), take.face_index, take.barycentric, faces)        # (K, L, 3)
    Kn = len(D)
    if R0 is None:
        R0, t0 = place_in_camera(None, np.asarray(neutral, np.float64), take.camera)
    x = np.concatenate([Rotation.from_matrix(R0).as_rotvec(), np.asarray(t0, np.float64), np.full(Kn, 0.05)])
    lo = np.concatenate([np.full(6, -np.inf), np.zeros(Kn) if bounded else np.full(Kn, -np.inf)])
    hi = np.concatenate([np.full(6, np.inf), np.ones(Kn) if bounded else np.full(Kn, np.inf)])
    T = len(take.points2d)
    W, Rs, ts = np.zeros((T, Kn)), np.zeros((T, 3, 3)), np.zeros((T, 3))
    for j in range(T):
        ok = take.weights[j] > 0
        p, Nj, Dj = take.points2d[j][ok], N[ok], D[:, ok]

        def model(x):
            R = Rotation.from_rotvec(x[:3]).as_matrix()
            local = Nj + np.tensordot(x[6:], Dj, axes=1)
            X = local @ R.T + x[3:6]
            return R, local, X

        def resid(x):
            _, _, X = model(x)
            return np.concatenate([fx * X[:, 0] / X[:, 2] + cx - p[:, 0], fy * X[:, 1] / X[:, 2] + cy - p[:, 1]])

        def jac(x):
            R, local, X = model(x)
            iz = 1 / X[:, 2]
            du = np.stack([fx * iz, np.zeros_like(iz), -fx * X[:, 0] * iz * iz], 1)     # (L, 3)
            dv = np.stack([np.zeros_like(iz), fy * iz, -fy * X[:, 1] * iz * iz], 1)
            y = local @ R.T
            # left-perturbation rotation derivative d X / d a = -[y]x (accurate near the current x)
            def rows(d):
                drot = np.cross(y, d)                 # d.(-[y]x a) = (y x d) . a
                dw = np.einsum("lc,klc->lk", d, Dj @ R.T)
                return np.concatenate([drot, d, dw], 1)
            Jr = np.concatenate([rows(du), rows(dv)], 0)
            # the parameters are a rotation vector, not a left perturbation: map through the Jacobian
            Jr[:, :3] = Jr[:, :3] @ _left_jacobian(x[:3])
            return Jr

        sol = least_squares(resid, np.clip(x, lo, hi), jac=jac, bounds=(lo, hi), method="trf", x_scale="jac",
                            xtol=1e-8, ftol=1e-8)
        x = sol.x
        W[j], Rs[j], ts[j] = x[6:], Rotation.from_rotvec(x[:3]).as_matrix(), x[3:6]
    local = neutral[None] + np.einsum("tk,kvc->tvc", W, deltas)
    return BlendshapeFit2D(W, Rs, ts, (np.einsum("tij,tvj->tvi", Rs, local) + ts[:, None]).astype(np.float32))


def _left_jacobian(v: np.ndarray) -> np.ndarray:
    """``d log(exp(a) exp(v)) ...``: the matrix ``J_l(v)`` with ``d exp(v) = [J_l(v) dv]x exp(v)``."""
    th = np.linalg.norm(v)
    S = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    if th < 1e-8:
        return np.eye(3) + 0.5 * S
    return np.eye(3) + (1 - np.cos(th)) / th ** 2 * S + (th - np.sin(th)) / th ** 3 * (S @ S)
