"""Performance retargeting (paper, Sec. 5.4): play a fit of actor A on actor B.

A and B are learned from blendshapes in correspondence (one topology, the same expressions). A fit of
A gives per frame the head transform T_g, the jaw transform T_b and the coefficient field
``w_j(c) = coeff0_j + F_W(z_j, c)`` (the frame's base coefficients plus
F_W's field) over A's template. B plays them as

    s_B(c_i) = T_g( LBS(s0_B(c_i), T_b, k_B(c_i)) + sum_e w_j,e(c_i^A) E_B,e(c_i) )

where vertex i of B's template ``c_i`` corresponds to vertex i of A's ``c_i^A``: the coefficient field
is read where A's fit defined it (A's template point and A's input normalisation), the anatomy is B's.
The jaw transform acts about B's own jaw pivot; the head transform is played as it is (both actors'
template frames are the head frame), so B sits where A sat in the camera.

The paper's disentangled outputs are :data:`PARTS`: ``jaw`` is the rigid jaw motion only
(``T_g(LBS(s0, T_b, k))``), ``soft_tissue`` the non-rigid deformation with the jaw at rest
(``T_g(s0 + sum w E)``).
"""

from __future__ import annotations

import torch

from models.aim import AnatomicalFaceModel
from models.fit import ActorAtPoints, FitSettings, SequenceFit, pose_face

PARTS = ("full", "jaw", "soft_tissue")


@torch.no_grad()
def retarget_points(source: AnatomicalFaceModel, source_points: torch.Tensor, target: AnatomicalFaceModel,
                    target_points: torch.Tensor, expression_order: list[int] | None = None) -> ActorAtPoints:
    """B's anatomy at its points, with F_W's input (points, normalisation) from A at the corresponding points.

    Args:
        source, target: the frozen models of A and B.
        source_points, target_points: ``(V, 3)`` mm, corresponding template points (row i <-> row i).
        expression_order: ``order[e]`` is B's expression column playing A's expression e (None: same order).
    """
    if source_points.shape != target_points.shape or source_points.shape[-1] != 3 or source_points.dim() != 2:
        raise ValueError(f"corresponding points must both be (V, 3); got {tuple(source_points.shape)} and "
                         f"{tuple(target_points.shape)}")
    a = target(target_points)
    expressions = a.expressions if expression_order is None else a.expressions[:, list(expression_order)]
    if expressions.shape[1] != source.config.n_expressions:
        raise ValueError(f"target plays {expressions.shape[1]} expressions, the source fit has "
                         f"{source.config.n_expressions}")
    return ActorAtPoints(points=source_points, neutral=a.neutral, skin_weight=a.skin_weight, expressions=expressions,
                         jaw_pivot=target.jaw_pivot, center=source.center, scale=float(source.config.scale))


def pose_part(actor: ActorAtPoints, head_R: torch.Tensor, head_t: torch.Tensor, jaw_R: torch.Tensor,
              jaw_t: torch.Tensor, coeffs: torch.Tensor, part: str = "full") -> torch.Tensor:
    """:func:`models.fit.pose_face` of one of :data:`PARTS` (shapes as there; ``(J, P, 3)`` mm out)."""
    if part == "full":
        return pose_face(actor, head_R, head_t, jaw_R, jaw_t, coeffs)
    if part == "jaw":
        return pose_face(actor, head_R, head_t, jaw_R, jaw_t, torch.zeros_like(coeffs))
    if part == "soft_tissue":
        eye = torch.eye(3, dtype=jaw_R.dtype, device=jaw_R.device).expand_as(jaw_R)
        return pose_face(actor, head_R, head_t, eye, torch.zeros_like(jaw_t), coeffs)
    raise ValueError(f"part must be one of {PARTS}, got {part!r}")


@torch.no_grad()
def window_vertices(state: dict, settings: FitSettings, actor: ActorAtPoints, part: str = "full"):
    """Vertices ``(J, V, 3)`` float32 numpy of one solved fit window (a :class:`SequenceFit` state) on ``actor``.

    The same evaluation as the fit's own outputs (``capture.fit.take``), one frame at a time.
    """
    import numpy as np

    state = {k: v.to(actor.points.device) for k, v in state.items()}
    J = state["codes"].shape[0]
    fit = SequenceFit(J, actor.n_expressions, settings, state["head_R0"], state["head_t0"])
    fit.load_state_dict(state)
    pose = fit.poses()
    out = np.empty((J, actor.points.shape[0], 3), np.float32)
    for j in range(J):
        sl = slice(j, j + 1)
        w = fit.coefficients(actor, frames=sl)
        out[j] = pose_part(actor, pose.head_R[sl], pose.head_t[sl], pose.jaw_R[sl], pose.jaw_t[sl], w,
                           part)[0].cpu().numpy()
    return out
