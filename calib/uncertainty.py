"""What a calibration knows: intrinsic covariance, predicted pixel uncertainty, coverage, model spread.

Pure math on a calibration's corners, poses and cameras (no files). Conventions as :mod:`calib.camera`
(pixel centres at integer coordinates, grids span ``[0, w-1] x [0, h-1]``).

- :func:`intrinsic_covariance` is the covariance of the estimated intrinsics (fx, fy, cx, cy and the
  model's free distortion terms), marginalised over the board poses: ``sigma^2 (J^T J)^-1`` at the
  solution, the Schur complement of the pose blocks, with the residual variance
  ``sigma^2 = sum r^2 / (2N - P)``. Its diagonal is what OpenCV reports as ``stdDeviationsIntrinsics``.
- :func:`pixel_uncertainty` propagates it to the image: for a pixel u the ray through u is held fixed
  and ``sigma(u) = sqrt(trace(J_u C J_u^T))`` with ``J_u = d pixel / d intrinsics`` (px, 1-sigma of the
  2-D position where the model sends that ray).
- :func:`projection_difference` compares two cameras over the image: ``|pi_b(pi_a^-1(u)) - u|``, where a
  ray seen at pixel u by camera a lands with camera b (the whole-image model error when a is the truth,
  the hold-out spread when b is a fold camera).
- :func:`coverage` counts used corners per cell and how far each part of the image is from the data.

**Up to the camera's rotation** (``align=True``, ``modulo_rotation=True``). A calibration fixes the
camera's axes only through its own board poses, so its intrinsics come with a small rotation of the
camera frame that the same views cannot tell apart: a shift of the principal point with all board
poses turned to match fits the corners almost as well. No use of a calibration that also solves the
pose of what it films (the head pose of every frame of a take) can see that rotation. So the
differences that matter are those left after the rotation of the rays that best aligns the two
cameras over the compared pixels: :func:`implied_rotation`, by least squares in pixels. This is how
mrcal compares two lens models and states a model's uncertainty ("projection diff" with the implied
transformation, at infinite range). :func:`pixel_uncertainty` with ``modulo_rotation`` removes from
every intrinsic direction the pixel motion that a rotation of the rays reproduces (the least-squares
fit over the same pixels, linearised); the remainder is what such a camera error does to the image.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calib.camera import Camera
from calib.models import DIST_NAMES, DistortionModel

#: Image corner names, in the order of :func:`image_corners`.
CORNER_NAMES = ("top-left", "top-right", "bottom-left", "bottom-right")


def pixel_grid(image_size: tuple[int, int], step: float = 16.0) -> tuple[np.ndarray, tuple[int, int]]:
    """(m, 2) float64 pixel positions on a regular grid including the image's edge pixels, and (nx, ny)."""
    w, h = image_size
    nx, ny = max(2, int(np.ceil((w - 1) / step)) + 1), max(2, int(np.ceil((h - 1) / step)) + 1)
    xs, ys = np.linspace(0.0, w - 1.0, nx), np.linspace(0.0, h - 1.0, ny)
    gx, gy = np.meshgrid(xs, ys)
    return np.stack([gx.ravel(), gy.ravel()], 1), (nx, ny)


def image_corners(image_size: tuple[int, int]) -> np.ndarray:
    w, h = image_size
    return np.array([[0.0, 0.0], [w - 1.0, 0.0], [0.0, h - 1.0], [w - 1.0, h - 1.0]])


def rays_of(camera: Camera, pixels: np.ndarray) -> np.ndarray:
    """(m, 2) normalised image coordinates (x/z, y/z) of the rays camera sees at ``pixels`` (m, 2)."""
    import cv2

    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    pts = np.ascontiguousarray(pixels, np.float64).reshape(-1, 1, 2)
    return cv2.undistortPointsIter(pts, camera.K, camera.dist, None, None, crit).reshape(-1, 2)


def project_rays(camera: Camera, rays: np.ndarray) -> np.ndarray:
    import cv2

    pts = np.column_stack([rays, np.ones(len(rays))]).reshape(-1, 1, 3)
    uv, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), camera.K, camera.dist)
    return uv.reshape(-1, 2)


def _rotated(rays: np.ndarray, rvec: np.ndarray) -> np.ndarray:
    """Normalised rays (m, 2) turned by the rotation vector ``rvec`` (3,), again as (x/z, y/z)."""
    import cv2

    v = np.column_stack([rays, np.ones(len(rays))]) @ cv2.Rodrigues(np.asarray(rvec, np.float64))[0].T
    return v[:, :2] / v[:, 2:]


def implied_rotation(reference: Camera, other: Camera, pixels: np.ndarray) -> np.ndarray:
    """(3,) rotation vector R that best aligns the cameras over ``pixels`` (m, 2): it minimises
    ``sum |pi_other(R pi_reference^-1(u)) - u|^2`` (px^2) by ``scipy.optimize.least_squares``.

    Rotations here are a fraction of a degree (calibration noise), so starting at zero converges.
    """
    from scipy.optimize import least_squares

    rays = rays_of(reference, pixels)
    pixels = np.asarray(pixels, np.float64)

    def residual(rvec: np.ndarray) -> np.ndarray:
        return (project_rays(other, _rotated(rays, rvec)) - pixels).ravel()

    return least_squares(residual, np.zeros(3), method="lm", xtol=1e-12, ftol=1e-12).x


def projection_difference(reference: Camera, other: Camera, pixels: np.ndarray, align: bool = False) -> np.ndarray:
    """(m,) px: where ``other`` projects the rays ``reference`` sees at ``pixels``, minus ``pixels``.

    With ``align`` the rays are first turned by :func:`implied_rotation` over the same pixels, so the
    difference is that left up to the camera's rotation (module docstring).
    """
    if tuple(reference.image_size) != tuple(other.image_size):
        raise ValueError(f"cameras of different image sizes {reference.image_size} and {other.image_size}")
    rays = rays_of(reference, pixels)
    if align:
        rays = _rotated(rays, implied_rotation(reference, other, pixels))
    return np.linalg.norm(project_rays(other, rays) - pixels, axis=1)


# ------------------------------------------------------------------------------------------ covariance
@dataclass(frozen=True)
class Covariance:
    """Covariance (p, p) of the free intrinsics ``names`` (fx, fy or f, cx, cy, distortion terms)."""

    names: tuple[str, ...]
    matrix: np.ndarray
    sigma_px: float  # residual standard deviation per coordinate

    def std(self) -> dict[str, float]:
        return {n: float(np.sqrt(max(self.matrix[k, k], 0.0))) for k, n in enumerate(self.names)}


def _intrinsic_columns(jac: np.ndarray, camera: Camera, model: DistortionModel, fix_principal_point: bool,
                       fix_aspect_ratio: bool) -> tuple[np.ndarray, tuple[str, ...]]:
    """Columns of cv2.projectPoints' jacobian (rvec 3, tvec 3, f 2, c 2, dist D) for the free intrinsics."""
    cols, names = [], []
    if fix_aspect_ratio:  # fy = a fx with a fixed
        cols.append(jac[:, 6] + (camera.fy / camera.fx) * jac[:, 7])
        names.append("f")
    else:
        cols += [jac[:, 6], jac[:, 7]]
        names += ["fx", "fy"]
    if not fix_principal_point:
        cols += [jac[:, 8], jac[:, 9]]
        names += ["cx", "cy"]
    for k in model.free_terms:
        cols.append(jac[:, 10 + k])
        names.append(DIST_NAMES[k])
    return np.stack(cols, 1), tuple(names)


def intrinsic_covariance(camera: Camera, model: DistortionModel, object_points: list[np.ndarray],
                         image_points: list[np.ndarray], rvecs: list[np.ndarray], tvecs: list[np.ndarray],
                         fix_principal_point: bool = False, fix_aspect_ratio: bool = False) -> Covariance:
    """Covariance of the free intrinsics at a calibration's solution (module docstring)."""
    import cv2

    dist = np.zeros(model.n_dist)
    dist[: len(camera.dist)] = camera.dist[: model.n_dist]
    sq, n_res, names = 0.0, 0, ()
    blocks = []
    for obj, img, r, t in zip(object_points, image_points, rvecs, tvecs):
        proj, jac = cv2.projectPoints(np.asarray(obj, np.float64).reshape(-1, 3), np.asarray(r, np.float64),
                                      np.asarray(t, np.float64), camera.K, dist)
        res = (proj.reshape(-1, 2) - np.asarray(img, np.float64).reshape(-1, 2)).ravel()
        sq += float(res @ res)
        n_res += res.size
        Ji, names = _intrinsic_columns(jac, camera, model, fix_principal_point, fix_aspect_ratio)
        Jp = jac[:, :6]
        blocks.append((Ji, Jp))
    p = blocks[0][0].shape[1]
    A = np.zeros((p, p))
    for Ji, Jp in blocks:
        B = Ji.T @ Jp
        C = Jp.T @ Jp
        A += Ji.T @ Ji - B @ np.linalg.solve(C, B.T)
    dof = max(1, n_res - p - 6 * len(blocks))
    sigma2 = sq / dof
    try:
        cov = sigma2 * np.linalg.inv(A)
    except np.linalg.LinAlgError:
        cov = np.full((p, p), np.inf)
    return Covariance(names, cov, float(np.sqrt(sigma2)))


def pixel_uncertainty(camera: Camera, model: DistortionModel, cov: Covariance, pixels: np.ndarray,
                      fix_principal_point: bool = False, fix_aspect_ratio: bool = False,
                      modulo_rotation: bool = False) -> np.ndarray:
    """(m,) px: 1-sigma of where the model sends the ray seen at each of ``pixels`` (module docstring);
    with ``modulo_rotation``, of what is left after the rotation that best aligns ``pixels`` as a whole."""
    import cv2

    dist = np.zeros(model.n_dist)
    dist[: len(camera.dist)] = camera.dist[: model.n_dist]
    rays = rays_of(camera, pixels)
    pts = np.column_stack([rays, np.ones(len(rays))]).reshape(-1, 1, 3)
    _uv, jac = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), camera.K, dist)
    J, names = _intrinsic_columns(jac, camera, model, fix_principal_point, fix_aspect_ratio)
    if names != cov.names:
        raise ValueError(f"covariance of {cov.names} does not match the model's intrinsics {names}")
    if modulo_rotation:
        G = jac[:, :3]  # (2m, 3) pixel motion per rotation of the rays (rvec at zero)
        J = J - G @ np.linalg.lstsq(G, J, rcond=None)[0]
    var = np.einsum("ip,pq,iq->i", J, cov.matrix, J).reshape(-1, 2).sum(1)
    return np.sqrt(np.maximum(var, 0.0))


def term_effects_px(camera: Camera, model: DistortionModel, cov: Covariance, fix_principal_point: bool = False,
                    fix_aspect_ratio: bool = False) -> dict[str, float]:
    """Pixels that 1 sigma of each distortion term alone moves the farthest image corner's ray."""
    import cv2

    corners = image_corners(camera.image_size)
    far = corners[np.argmax(np.linalg.norm(corners - [camera.cx, camera.cy], axis=1))]
    dist = np.zeros(model.n_dist)
    dist[: len(camera.dist)] = camera.dist[: model.n_dist]
    ray = rays_of(camera, far[None])
    _uv, jac = cv2.projectPoints(np.array([[[ray[0, 0], ray[0, 1], 1.0]]]), np.zeros(3), np.zeros(3), camera.K, dist)
    J, names = _intrinsic_columns(jac, camera, model, fix_principal_point, fix_aspect_ratio)
    std = cov.std()
    return {n: float(np.linalg.norm(J[:, k]) * std[n]) for k, n in enumerate(names) if n in DIST_NAMES}


# ------------------------------------------------------------------------------------------- coverage
@dataclass(frozen=True)
class Coverage:
    counts: np.ndarray  # (gy, gx) used corners per cell
    cell_px: float  # cell side in pixels
    corner_gaps_px: dict[str, float]  # distance from each image corner to the nearest used board corner
    uncovered_fraction: float  # of the image farther than ``reach_px`` from every used corner
    reach_px: float


def coverage(points: list[np.ndarray], image_size: tuple[int, int], cols: int = 16,
             reach_fraction: float = 0.05) -> Coverage:
    """Corner density per cell and gaps; ``reach_fraction`` of the image diagonal counts as covered."""
    from scipy.spatial import cKDTree

    w, h = image_size
    cell = w / cols
    gx, gy = cols, max(1, int(round(h / cell)))
    allp = np.concatenate(points) if points else np.zeros((0, 2))
    counts = np.zeros((gy, gx), np.int64)
    if len(allp):
        ix = np.clip(((allp[:, 0] + 0.5) / w * gx).astype(int), 0, gx - 1)
        iy = np.clip(((allp[:, 1] + 0.5) / h * gy).astype(int), 0, gy - 1)
        np.add.at(counts, (iy, ix), 1)
    reach = reach_fraction * float(np.hypot(w, h))
    grid, _ = pixel_grid(image_size, max(4.0, np.hypot(w, h) / 200))
    if len(allp):
        tree = cKDTree(allp)
        gaps = {n: float(tree.query(c)[0]) for n, c in zip(CORNER_NAMES, image_corners(image_size))}
        uncovered = float(np.mean(tree.query(grid)[0] > reach))
    else:
        gaps = {n: float("inf") for n in CORNER_NAMES}
        uncovered = 1.0
    return Coverage(counts, cell, gaps, uncovered, reach)
