"""The actor as a blend-shape rig: the pure math behind ``curves.csv`` and the UsdSkel animation.

The fitted face of a frame is (``models.fit.pose_face``, camera frame, mm)::

    s*(c) = T_g( LBS(s0(c), T_b, k(c)) + sum_i w_i(c) E_i(c) )

with the head transform ``T_g: x -> head_R x + head_t``, the jaw transform ``T_b`` about the actor's
jaw pivot p (``x -> jaw_R (x - p) + p + jaw_t``), the jaw skinning weight k, and coefficients
``w_i(c) = b_i + F_W(z, c)_i``: a per-frame *base* ``b`` (one weight per expression, the same at every
point) plus the network's spatially varying correction. A rig plays the base:

    base(c) = T_g( s0 + k (T_b(s0) - s0) + sum_i b_i E_i )

Every term inside ``T_g`` is linear in a weight, so the whole base is a blend-shape rig with one rigid
joint for the head, exactly (no approximation):

* the expression shapes ``E_i`` with weights ``b_i`` (the actor's names: ``jawOpen``, ``mouthSmile_L``...);
* the jaw: ``k (T_b(s0) - s0) = k ((jaw_R - I)(s0 - p) + jaw_t)`` is linear in the twelve numbers
  ``(jaw_R - I)_ab`` and ``jaw_t_a``, so twelve shapes ``J_ab = k e_a (s0 - p)_b`` and ``J_a = k e_a``
  with those numbers as weights reproduce the actor's jaw skinning exactly at any angle. (A jaw *joint*
  would not: UsdSkel adds blend shapes before skinning, so the jaw would turn the expression offsets
  of the chin with it, while the actor adds them after: 0.9 mm off on the demo take, jaw within 7 deg.)

What the rig does not play is the network's local detail ``T_g(sum_i F_W_i(c) E_i(c))``; the exported
meshes carry it. On 2D fits with the default preset F_W stays at zero (the base is the whole fit); on
3D fits (``capture fit3d``) it is the fit's own base-versus-full difference.

Angles for ``curves.csv`` follow the synthetic takes' convention (:mod:`capture.synth.scene`): the head
rotation relative to a frontal view is ``R_FRONT.T @ head_R = Rz(roll) Ry(yaw) Rx(-pitch)`` in the
template frame (x the actor's left, y up, z out of the face); the jaw rotation ``jaw_R`` (head frame) is
decomposed the same way, so a jaw opening is a negative pitch (the chin turns down).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: The head rotation of a frontal view (template frame -> OpenCV camera frame), see capture.synth.scene.
R_FRONT = np.diag([1.0, -1.0, -1.0])
#: Names of the twelve exact jaw shapes (weights: entries of jaw_R - I, row-major, then jaw_t in mm).
JAW_SHAPE_NAMES = tuple([f"jaw_R{a}{b}" for a in range(3) for b in range(3)] + ["jaw_tx", "jaw_ty", "jaw_tz"])


@dataclass(frozen=True)
class FaceRig:
    """The frozen actor evaluated at its template vertices (head frame, mm).

    Attributes:
        neutral: ``(V, 3)`` the neutral skin s0.
        skin_weight: ``(V,)`` jaw skinning weight k (0 skull .. 1 jaw).
        expressions: ``(E, V, 3)`` expression shapes E_i (offsets added after the jaw skinning).
        names: ``E`` expression names (the actor's shape names without the neutral).
        jaw_pivot: ``(3,)`` centre of the jaw rotation.
    """

    neutral: np.ndarray
    skin_weight: np.ndarray
    expressions: np.ndarray
    names: tuple[str, ...]
    jaw_pivot: np.ndarray

    def __post_init__(self) -> None:
        V = np.shape(self.neutral)[0]
        if np.shape(self.neutral) != (V, 3) or np.shape(self.skin_weight) != (V,):
            raise ValueError(f"neutral (V, 3) and skin_weight (V,) expected, got {np.shape(self.neutral)}, "
                             f"{np.shape(self.skin_weight)}")
        if np.shape(self.expressions) != (len(self.names), V, 3):
            raise ValueError(f"expressions expected ({len(self.names)}, {V}, 3), got {np.shape(self.expressions)}")

    @property
    def n_vertices(self) -> int:
        return int(np.shape(self.neutral)[0])

    @classmethod
    def from_actor(cls, actor) -> "FaceRig":
        """``actor`` (:class:`capture.actor.package.Actor`) at every template vertex (its cached query)."""
        model = actor.model
        a = actor.at_template()
        neutral_name = actor.metadata.get("neutral", actor.shape_names[0])
        names = tuple(n for n in actor.shape_names if n != neutral_name)
        expr = a.expressions.detach().cpu().double().numpy().transpose(1, 0, 2)      # (E, V, 3)
        if len(names) != expr.shape[0]:
            names = tuple(f"expression_{i}" for i in range(expr.shape[0]))
        return cls(a.neutral.detach().cpu().double().numpy(), a.skin_weight.detach().cpu().double().numpy(),
                   expr, names, model.jaw_pivot.detach().cpu().double().numpy().reshape(3))


def jaw_shapes(rig: FaceRig) -> np.ndarray:
    """``(12, V, 3)`` the exact jaw shapes (see the module docstring), in :data:`JAW_SHAPE_NAMES` order."""
    k = np.asarray(rig.skin_weight, np.float64)[:, None]
    rel = np.asarray(rig.neutral, np.float64) - np.asarray(rig.jaw_pivot, np.float64)
    out = np.zeros((12, rig.n_vertices, 3))
    for a in range(3):
        for b in range(3):
            out[3 * a + b, :, a] = k[:, 0] * rel[:, b]
        out[9 + a, :, a] = k[:, 0]
    return out


def jaw_weights(jaw_R: np.ndarray, jaw_t: np.ndarray) -> np.ndarray:
    """``(..., 12)`` weights of :func:`jaw_shapes` for jaw rotations ``(..., 3, 3)`` and translations ``(..., 3)``."""
    R = np.asarray(jaw_R, np.float64)
    d = (R - np.eye(3)).reshape(R.shape[:-2] + (9,))
    return np.concatenate([d, np.asarray(jaw_t, np.float64)], -1)


def base_vertices_head(rig: FaceRig, jaw_R: np.ndarray, jaw_t: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """``(V, 3)`` the base face in the head frame: ``LBS(s0, T_b, k) + sum_i b_i E_i`` (mm)."""
    s0 = np.asarray(rig.neutral, np.float64)
    p = np.asarray(rig.jaw_pivot, np.float64)
    moved = (s0 - p) @ np.asarray(jaw_R, np.float64).T + p + np.asarray(jaw_t, np.float64)
    skinned = s0 + rig.skin_weight[:, None] * (moved - s0)
    return skinned + np.einsum("e,evc->vc", np.asarray(weights, np.float64), rig.expressions)


def base_vertices(rig: FaceRig, head_R, head_t, jaw_R, jaw_t, weights) -> np.ndarray:
    """``(V, 3)`` the base face in the camera frame (mm): ``head_R @ base_head + head_t``."""
    return base_vertices_head(rig, jaw_R, jaw_t, weights) @ np.asarray(head_R, np.float64).T + \
        np.asarray(head_t, np.float64)


def head_angles_deg(head_R: np.ndarray) -> np.ndarray:
    """``(..., 3)`` (yaw, pitch, roll) in degrees of head rotations ``(..., 3, 3)`` (camera frame).

    ``R_FRONT.T @ head_R = Rz(roll) Ry(yaw) Rx(-pitch)`` as in :func:`capture.synth.scene.head_rotation`:
    positive yaw turns the face to the actor's left (the image's right), positive pitch tilts it up.
    """
    R = np.asarray(head_R, np.float64)
    local = np.einsum("ij,...jk->...ik", R_FRONT.T, R)
    return _zyx_angles(local)


def jaw_angles_deg(jaw_R: np.ndarray) -> np.ndarray:
    """``(..., 3)`` (yaw, pitch, roll) in degrees of jaw rotations ``(..., 3, 3)`` in the head frame
    (``jaw_R = Rz(roll) Ry(yaw) Rx(-pitch)``; an opening jaw has a negative pitch)."""
    return _zyx_angles(np.asarray(jaw_R, np.float64))


def _zyx_angles(local: np.ndarray) -> np.ndarray:
    """``(..., 3)`` (yaw, pitch, roll) degrees of rotations ``(..., 3, 3) = Rz(roll) Ry(yaw) Rx(-pitch)``;
    NaN where a matrix is not finite. In closed form (``R[2, 0] = -sin yaw``; scipy's import costs a run's
    report 0.2 s); away from yaw = +-90 deg, which a face never reaches, it equals scipy's
    ``Rotation.as_euler("ZYX")`` (tests/test_curves_rig.py)."""
    R = np.asarray(local, np.float64)
    with np.errstate(invalid="ignore"):
        yaw = np.degrees(np.arcsin(np.clip(-R[..., 2, 0], -1.0, 1.0)))
        roll = np.degrees(np.arctan2(R[..., 1, 0], R[..., 0, 0]))
        pitch = -np.degrees(np.arctan2(R[..., 2, 1], R[..., 2, 2]))
    out = np.stack([yaw, pitch, roll], -1)
    out[~np.isfinite(R).all((-1, -2))] = np.nan
    return out


def frame_base_weights(fit, n_expressions: int) -> np.ndarray:
    """``(E,)`` the per-frame base coefficients of a frame fit (NaN when the frame has none).

    ``fit.coefficients_base`` when the fit stored it; otherwise (fits cached before it existed) the
    mean over the fit points of ``coefficients_landmarks``, which is the base exactly while F_W is at
    its zero start (every 2D fit of the default preset)."""
    b = getattr(fit, "coefficients_base", None)
    if b is not None and np.size(b) == n_expressions and np.isfinite(np.asarray(b, np.float64)).all():
        return np.asarray(b, np.float64).reshape(n_expressions)
    w = getattr(fit, "coefficients_landmarks", None)
    if w is None or getattr(fit, "status", "fitted") == "skipped":
        return np.full(n_expressions, np.nan)
    w = np.asarray(w, np.float64).reshape(-1, n_expressions)
    return w.mean(0) if len(w) else np.full(n_expressions, np.nan)
