"""Rotations and rigid transforms: the 6D parameterisation and its inverse.

Conventions (column vectors): a point x maps to ``R @ x + t``. The continuous 6D representation of
Zhou et al. (CVPR 2019) is the first two *columns* of R, concatenated: ``[R[:, 0], R[:, 1]]``.
:func:`rot6d_to_matrix` orthonormalises them by Gram-Schmidt and completes the frame with a cross
product, so any 6-vector whose two halves are not parallel maps to a proper rotation (det = +1).
6D is an internal parameterisation only: files store 3x3 matrices or axis-angle (DESIGN.md).
"""

from __future__ import annotations

import torch

from models.checks import check_shape

IDENTITY_6D = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0)


def rot6d_to_matrix(x: torch.Tensor) -> torch.Tensor:
    """Map 6D rotation vectors ``(*, 6)`` to rotation matrices ``(*, 3, 3)``.

    Example:
        >>> rot6d_to_matrix(torch.tensor(IDENTITY_6D))
        tensor([[1., 0., 0.],
                [0., 1., 0.],
                [0., 0., 1.]])
    """
    check_shape(x, "*,6", "x")
    a1, a2 = x[..., :3], x[..., 3:]
    b1 = torch.nn.functional.normalize(a1, dim=-1)
    a2 = a2 - (b1 * a2).sum(-1, keepdim=True) * b1
    b2 = torch.nn.functional.normalize(a2, dim=-1)
    b3 = torch.linalg.cross(b1, b2, dim=-1)
    return torch.stack([b1, b2, b3], dim=-1)


def matrix_to_rot6d(R: torch.Tensor) -> torch.Tensor:
    """Map rotation matrices ``(*, 3, 3)`` to their 6D representation ``(*, 6)`` (first two columns)."""
    check_shape(R, "*,3,3", "R")
    return torch.cat([R[..., :, 0], R[..., :, 1]], dim=-1)


def identity_6d(*batch: int, dtype=torch.float32, device=None) -> torch.Tensor:
    """Identity rotations in 6D, shape ``(*batch, 6)``."""
    eye = torch.tensor(IDENTITY_6D, dtype=dtype, device=device)
    return eye.expand(*batch, 6).clone()


def apply_rigid(points: torch.Tensor, R: torch.Tensor, t: torch.Tensor,
                pivot: torch.Tensor | None = None) -> torch.Tensor:
    """Apply ``x -> R (x - pivot) + pivot + t`` to points.

    Args:
        points: ``(*, P, 3)``.
        R: ``(*, 3, 3)`` rotations (broadcast over the batch dimensions of ``points``).
        t: ``(*, 3)`` translations.
        pivot: ``(3,)`` centre of rotation; the origin when None.

    Returns:
        ``(*, P, 3)`` transformed points.
    """
    check_shape(points, "*,P,3", "points")
    check_shape(R, "*,3,3", "R")
    check_shape(t, "*,3", "t")
    if pivot is not None:
        points = points - pivot
    # R @ points^T: a product over the points' long axis. As einsum("...ij,...pj->...pi") (points @ R^T, a
    # product with 3 columns) it ran 3-4x slower on the CPU: 7.5 against 1.8 ms for 30 frames of 9,409
    # points on one core, with the same results up to rounding (BENCHMARKS.md, streaming pipeline, sixteenth round)
    out = torch.matmul(R, points.transpose(-1, -2)).transpose(-1, -2) + t.unsqueeze(-2)
    if pivot is not None:
        out = out + pivot
    return out


def kabsch(src: torch.Tensor, dst: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Least-squares rigid transform with ``dst ~ R @ src + t`` (Kabsch / Umeyama without scale).

    Args:
        src, dst: ``(*, P, 3)`` corresponding points, P >= 3 not collinear.

    Returns:
        R ``(*, 3, 3)`` (a proper rotation, det = +1) and t ``(*, 3)``.
    """
    check_shape(src, "*,P,3", "src")
    check_shape(dst, "*,P,3", "dst")
    mu_s, mu_d = src.mean(-2, keepdim=True), dst.mean(-2, keepdim=True)
    H = (src - mu_s).transpose(-1, -2) @ (dst - mu_d)
    U, _, Vh = torch.linalg.svd(H)
    d = torch.sign(torch.linalg.det(Vh.transpose(-1, -2) @ U.transpose(-1, -2)))
    D = torch.diag_embed(torch.stack([torch.ones_like(d), torch.ones_like(d), d], -1))
    R = Vh.transpose(-1, -2) @ D @ U.transpose(-1, -2)
    t = mu_d.squeeze(-2) - (R @ mu_s.transpose(-1, -2)).squeeze(-1)
    return R, t


def so3_exp(v: torch.Tensor) -> torch.Tensor:
    """Rotation matrices ``(*, 3, 3)`` of rotation vectors ``v (*, 3)`` (radians): Rodrigues' formula
    ``I + A [v]x + B [v]x^2`` with its Taylor series near 0 (differentiable everywhere)."""
    t2 = (v * v).sum(-1)
    small = t2 < 1e-6
    safe = torch.where(small, torch.ones_like(t2), t2)
    t = torch.sqrt(safe)
    A = torch.where(small, 1 - t2 / 6 + t2 * t2 / 120, torch.sin(t) / t)
    B = torch.where(small, 0.5 - t2 / 24 + t2 * t2 / 720, (1 - torch.cos(t)) / safe)
    S = skew(v)
    eye = torch.eye(3, dtype=v.dtype, device=v.device)
    return eye + A[..., None, None] * S + B[..., None, None] * (S @ S)


def skew(v: torch.Tensor) -> torch.Tensor:
    """``[v]x (*, 3, 3)`` with ``[v]x a = v x a``."""
    z = torch.zeros_like(v[..., 0])
    return torch.stack([torch.stack([z, -v[..., 2], v[..., 1]], -1),
                        torch.stack([v[..., 2], z, -v[..., 0]], -1),
                        torch.stack([-v[..., 1], v[..., 0], z], -1)], -2)
