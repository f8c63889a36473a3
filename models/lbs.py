"""Linear blend skinning with one jaw bone.

The skull is the rest frame (identity); the jaw moves rigidly by ``T_b(x) = R (x - pivot) + pivot + t``.
A point with jaw skinning weight k moves to ``(1 - k) x + k T_b(x)``: LBS with two bones whose
weights sum to one. The pivot is a fixed centre of rotation (near the temporomandibular joint)
that conditions the rotation; any rigid motion is still reachable through ``t``.
"""

from __future__ import annotations

import torch

from models.checks import check_shapes
from models.rotation import apply_rigid


def lbs_jaw(points: torch.Tensor, weights: torch.Tensor, R: torch.Tensor, t: torch.Tensor,
            pivot: torch.Tensor | None = None) -> torch.Tensor:
    """Skin points with one jaw bone.

    Args:
        points: ``(*, P, 3)`` rest positions (mm).
        weights: ``(*, P)`` jaw skinning weights k (0 = skull, 1 = jaw).
        R: ``(*, 3, 3)`` jaw rotation; t: ``(*, 3)`` jaw translation (mm); pivot: ``(3,)``.

    Returns:
        ``(*, P, 3)`` skinned positions.
    """
    check_shapes({"points": (points, "*,P,3"), "weights": (weights, "*,P")})
    moved = apply_rigid(points, R, t, pivot)
    k = weights.unsqueeze(-1)
    return points + k * (moved - points)
