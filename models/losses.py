"""The five model-learning losses of the paper (Sec. 4.1.1), as pure functions.

Every loss is a mean of squared residuals over its points (and shapes), multiplied by its weight.

Units. The paper's weights balance losses with lengths in the paper's unit against unit-free ones
(normals, skinning weights). We keep lengths in millimetres everywhere but divide every length
residual by ``length_unit_mm`` (default 10 mm, i.e. centimetres, the unit of the paper's
registered face data and of ICT FaceKit) before squaring, so the paper's weights keep their
relative meaning for faces given in any unit. ``length_unit_mm`` is part of the saved settings.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch

from models.checks import check_shapes


@dataclass(frozen=True)
class LossWeights:
    """Loss weights; defaults are the paper's."""

    skin: float = 1.0            # lambda_S
    bone: float = 1.0            # lambda_b
    thickness: float = 1.0       # lambda_d
    normal: float = 1.0          # lambda_n
    thickness_reg: float = 7.5e-4  # lambda_D^Reg
    symmetry: float = 1e-4       # lambda_sym
    forehead_skinning: float = 1e2  # lambda_K
    length_unit_mm: float = 10.0

    def to_dict(self) -> dict:
        return asdict(self)


def _point_mean(values: torch.Tensor, weights: torch.Tensor | None) -> torch.Tensor:
    """Mean over the last axis (points), each point counted ``weights[p]`` times when given.

    With points drawn at random with probability ``q_p`` and ``weights = 1 / (V q_p)`` this is an
    unbiased estimate of the mean over all V points (importance sampling, :mod:`models.train`).
    """
    if weights is None:
        return values.mean()
    return (values * weights).mean()


def skin_position_loss(pred: torch.Tensor, target: torch.Tensor, unit: float,
                       weights: torch.Tensor | None = None) -> torch.Tensor:
    """``mean ||s~ - s||^2`` over shapes and points; pred, target ``(S, P, 3)`` mm; weights ``(P,)``."""
    check_shapes({"pred": (pred, "*,P,3"), "target": (target, "*,P,3")})
    return _point_mean(((pred - target) / unit).square().sum(-1), weights)


def anatomy_losses(bone: torch.Tensor, thickness: torch.Tensor, normal: torch.Tensor,
                   bone_target: torch.Tensor, thickness_target: torch.Tensor, normal_target: torch.Tensor,
                   unit: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The anatomy regulariser's three terms on M constrained points.

    Args: predicted and target bone points ``(M, 3)`` mm, thickness ``(M,)`` mm, normals ``(M, 3)``.
    Returns: (bone term, thickness term, normal term), each a mean of squared residuals.
    """
    check_shapes({"bone": (bone, "M,3"), "thickness": (thickness, "M"), "normal": (normal, "M,3"),
                  "bone_target": (bone_target, "M,3"), "thickness_target": (thickness_target, "M"),
                  "normal_target": (normal_target, "M,3")})
    if bone.shape[0] == 0:
        zero = bone.sum() * 0.0
        return zero, zero, zero
    lb = ((bone - bone_target) / unit).square().sum(-1).mean()
    ld = ((thickness - thickness_target) / unit).square().mean()
    ln = (normal - normal_target).square().sum(-1).mean()
    return lb, ld, ln


def thickness_regularizer(thickness: torch.Tensor, unit: float, weights: torch.Tensor | None = None) -> torch.Tensor:
    """``mean d^2``: keeps the tissue thin where nothing else asks for thickness; thickness ``(P,)``."""
    return _point_mean((thickness / unit).square(), weights)


def symmetry_loss(bone_of_reflected: torch.Tensor, reflected_bone: torch.Tensor, unit: float,
                  weights: torch.Tensor | None = None) -> torch.Tensor:
    """``mean ||B(R(c)) - R(B(c))||^2``; both ``(P, 3)`` mm."""
    check_shapes({"B(R(c))": (bone_of_reflected, "P,3"), "R(B(c))": (reflected_bone, "P,3")})
    return _point_mean(((bone_of_reflected - reflected_bone) / unit).square().sum(-1), weights)


def skinning_weight_loss(skin_weight_forehead: torch.Tensor) -> torch.Tensor:
    """``mean K(c*)^2`` over forehead points: the jaw must not move the forehead (0 when none)."""
    if skin_weight_forehead.numel() == 0:
        return skin_weight_forehead.sum() * 0.0
    return skin_weight_forehead.square().mean()
