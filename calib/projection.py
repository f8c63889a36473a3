"""Differentiable, batched projection through the calibrated camera (torch, built on kornia).

Conventions (the one place they are stated for code that projects):

- Points are **camera coordinates in millimetres**, OpenCV axes: x right, y down, z forward
  (the camera looks along +z). Points are row-stacked ``(*, N, 3)``; matrices act on column
  vectors, ``u ~ K @ [x/z, y/z, 1]^T``.
- ``K`` is ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` in pixels; ``dist`` is OpenCV's vector
  ``(k1, k2, p1, p2[, k3[, k4, k5, k6[, s1, s2, s3, s4[, tau_x, tau_y]]]])`` of length 0
  (no distortion), 4, 5, 8, 12 or 14, applied to the normalised coordinates ``(x/z, y/z)``
  exactly as ``cv2.projectPoints`` does.
- Pixel centres are at integer coordinates (OpenCV and kornia agree): pixel ``(0, 0)`` covers
  ``[-0.5, 0.5]^2``. Results are ``(u, v)`` = (column, row).
- Points with ``|z| <= 1e-8`` are not divided (kornia's and OpenCV's rule) and points behind the
  camera (``z < 0``) project through the origin; callers mask them with ``points[..., 2] > 0``.

Foreign conventions are converted here and nowhere else: :func:`camera_tensors` turns a
:class:`~calib.camera.Camera` (numpy, float64) into tensors on the caller's device and dtype, and
OpenCV and kornia need no conversion between each other. Batch dimensions broadcast only through
:func:`broadcast_camera`, which checks them and names the mismatch.

Both functions are differentiable with respect to points, ``K`` and ``dist``, follow the device
and dtype of ``points``, and add no copies beyond kornia's element-wise arithmetic: ``K`` and
``dist`` are expanded as views, never materialised per point.
"""

from __future__ import annotations

import numpy as np
import torch
from kornia.geometry.calibration import distort_points, undistort_points as _kornia_undistort
from kornia.geometry.camera.perspective import project_points as _kornia_project
from kornia.geometry.conversions import convert_points_from_homogeneous

from calib.camera import DIST_LENGTHS, Camera

__all__ = ["project_points", "undistort_points", "camera_tensors", "broadcast_camera"]


def camera_tensors(
    camera: Camera, dtype: torch.dtype = torch.float32, device: torch.device | str | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(K (3, 3), dist (D,))`` of ``camera`` as tensors, ready for :func:`project_points`."""
    # copies: the camera's arrays are read-only and tensors must not alias them
    K = torch.tensor(camera.K.copy(), dtype=dtype, device=device)
    dist = torch.tensor(camera.dist.copy(), dtype=dtype, device=device)
    return K, dist


def broadcast_camera(
    points: torch.Tensor, K: torch.Tensor, dist: torch.Tensor | None, point_dim: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """Check shapes and expand (as views) ``K`` (*, 3, 3) and ``dist`` (*, D) to the batch of ``points``.

    ``points`` is ``(*, N, point_dim)``. The batch dimensions ``*`` of the three arguments must
    broadcast (e.g. points (F, N, 3) with one K (3, 3), or per-frame K (F, 3, 3)). Raises
    ``ValueError`` naming the expected and actual shapes otherwise.
    """
    if not isinstance(points, torch.Tensor) or not isinstance(K, torch.Tensor):
        raise TypeError("points and K must be torch tensors")
    if points.dim() < 2 or points.shape[-1] != point_dim:
        raise ValueError(f"points must have shape (*, N, {point_dim}), got {tuple(points.shape)}")
    if K.dim() < 2 or K.shape[-2:] != (3, 3):
        raise ValueError(f"K must have shape (*, 3, 3), got {tuple(K.shape)}")
    if dist is not None:
        if not isinstance(dist, torch.Tensor):
            raise TypeError("dist must be a torch tensor or None")
        if dist.dim() < 1 or dist.shape[-1] not in DIST_LENGTHS:
            raise ValueError(
                f"dist must have shape (*, D) with D in {DIST_LENGTHS} (OpenCV order), got {tuple(dist.shape)}"
            )
        if dist.shape[-1] == 0:
            dist = None
    for name, t in (("K", K), ("dist", dist)):
        if t is not None and (t.dtype != points.dtype or t.device != points.device):
            raise ValueError(
                f"{name} is {t.dtype} on {t.device} but points are {points.dtype} on {points.device}; "
                "convert with camera_tensors(camera, dtype, device)"
            )
    shapes = [points.shape[:-2], K.shape[:-2]] + ([dist.shape[:-1]] if dist is not None else [])
    try:   # numpy's: torch.broadcast_shapes imports torch.fx and sympy on first use (0.8 s)
        batch = np.broadcast_shapes(*shapes)
    except ValueError:
        raise ValueError(
            "batch dimensions do not broadcast: points (*, N, {}) {}, K (*, 3, 3) {}{}".format(
                point_dim, tuple(points.shape), tuple(K.shape),
                "" if dist is None else f", dist (*, D) {tuple(dist.shape)}",
            )
        ) from None
    points = points.expand(*batch, *points.shape[-2:])
    K = K.expand(*batch, 3, 3)
    if dist is not None:
        dist = dist.expand(*batch, dist.shape[-1])
    return points, K, dist


def project_points(points: torch.Tensor, K: torch.Tensor, dist: torch.Tensor | None = None) -> torch.Tensor:
    """Project camera-frame points (mm) to distorted pixels, as ``cv2.projectPoints`` with rvec=tvec=0.

    Args:
        points: ``(*, N, 3)`` camera coordinates (x right, y down, z forward), z > 0.
        K: ``(*, 3, 3)`` intrinsics; batch dims broadcast with those of ``points``.
        dist: ``(*, D)`` OpenCV distortion, D in (0, 4, 5, 8, 12, 14), or ``None``.

    Returns:
        ``(B, N, 2)`` pixel coordinates ``(u, v)``, ``B`` the broadcast batch shape.

    Example:
        >>> K = torch.tensor([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
        >>> project_points(torch.tensor([[10.0, -20.0, 1000.0]]), K, torch.zeros(5))
        tensor([[325., 230.]])
    """
    points, K, dist = broadcast_camera(points, K, dist, 3)
    if dist is None:
        return _kornia_project(points, K)
    xy = convert_points_from_homogeneous(points)  # (*, N, 2) on the z = 1 plane
    # kornia's distort_points maps incoming points to the normalised plane with ``new_K`` and the
    # distorted normalised points to pixels with ``K``; our points already are normalised, so
    # ``new_K`` is the identity (a broadcast view, no per-batch copy).
    eye = torch.eye(3, dtype=points.dtype, device=points.device).expand_as(K)
    return distort_points(xy, K, dist, new_K=eye)


def undistort_points(
    pixels: torch.Tensor, K: torch.Tensor, dist: torch.Tensor | None = None, num_iters: int = 20
) -> torch.Tensor:
    """Remove lens distortion from pixel coordinates: the inverse of the distortion in :func:`project_points`.

    Args:
        pixels: ``(*, N, 2)`` observed (distorted) pixel coordinates.
        K: ``(*, 3, 3)`` intrinsics.
        dist: ``(*, D)`` OpenCV distortion or ``None`` (then the pixels are returned as they are).
        num_iters: fixed-point iterations (kornia's, as OpenCV's ``undistortPoints``); 20 reaches
            1e-6 px for ordinary lenses (|k1| < 0.5 inside the image); strong fisheyes need more.

    Returns:
        ``(B, N, 2)`` undistorted pixel coordinates with the same ``K`` (``project_points`` without
        distortion would give them). Divide out ``K`` for normalised rays.
    """
    pixels, K, dist = broadcast_camera(pixels, K, dist, 2)
    if dist is None:
        return pixels
    return _kornia_undistort(pixels, K, dist, num_iters=num_iters)
