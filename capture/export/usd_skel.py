"""The take as a UsdSkel blend-shape rig inside ``take.usdc`` (``--formats curves``).

Beside the baked mesh ``/Take/Face`` (:mod:`capture.export.usd`), the rig plays the fit's per-frame
*base* (:mod:`capture.export.rig`) in any USD viewer or DCC that evaluates UsdSkel::

    /Take/Rig                    SkelRoot
    /Take/Rig/Skeleton           Skeleton, one joint "head" (bind and rest transforms identity),
                                 skel:animationSource -> /Take/Rig/Animation
    /Take/Rig/Animation          SkelAnimation: the head joint's translation / rotation (time-sampled),
                                 blendShapes (the actor's expression names + the 12 exact jaw shapes
                                 jaw_R00..jaw_R22, jaw_tx..jaw_tz), blendShapeWeights (time-sampled)
    /Take/Rig/Face               Mesh bound to the skeleton (every vertex rigidly to "head"): rest points
                                 = the actor's neutral in its template frame, skel:blendShapeTargets ->
    /Take/Rig/Face/<shape>       BlendShape prims with the shapes' offsets (mm, template frame)

Axes: the template (head) frame is y up (x the actor's left, z out of the face), USD's own convention,
so rest points and offsets are written as they are; the head joint carries the head pose converted to
the stage's axes, ``p_usd = CAMERA_TO_USD @ (head_R @ x + head_t)`` (the matrix is passed in by
:mod:`capture.export.usd`, the one place that defines it): rotation ``CAMERA_TO_USD @ head_R``,
translation ``CAMERA_TO_USD @ head_t``. The rig then lands on the baked mesh wherever the fit has no
local detail (``/Take/Face`` stays the exact per-frame result).

Frames without a fit get no samples and the rig is time-sampled ``invisible`` there, like the baked
mesh. Both are visible otherwise and occupy the same place: hide one of them in a viewer
(``/Take/Face`` is the exact per-frame result, the rig is what an animator edits).
"""

from __future__ import annotations

import numpy as np

from capture.export.rig import JAW_SHAPE_NAMES, FaceRig, frame_base_weights, jaw_shapes, jaw_weights

RIG_PRIM = "/Take/Rig"
SKELETON = "Skeleton"
ANIMATION = "Animation"
FACE = "Face"
JOINT = "head"


def _token(name: str) -> str:
    """A valid USD prim name for a shape name (letters, digits, underscores; no leading digit)."""
    out = "".join(ch if ch.isalnum() or ch == "_" else "_" for ch in name)
    return out if out and not out[0].isdigit() else f"_{out}"


def head_joint_transform(head_R: np.ndarray, head_t: np.ndarray, to_stage: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The head joint's (quaternion ``(w, x, y, z)``, translation ``(3,)`` mm) on the stage's axes
    (``to_stage``: the camera-to-stage rotation, :data:`capture.export.usd.CAMERA_TO_USD`)."""
    from scipy.spatial.transform import Rotation

    C = np.asarray(to_stage, np.float64)
    R = C @ np.asarray(head_R, np.float64)
    x, y, z, w = Rotation.from_matrix(R).as_quat()
    return np.array([w, x, y, z]), C @ np.asarray(head_t, np.float64)


class SkelRigWriter:
    """Authors the rig on an open stage and adds one sample per frame (see the module docstring)."""

    def __init__(self, stage, rig: FaceRig, faces: np.ndarray, to_stage: np.ndarray, root: str = RIG_PRIM):
        from pxr import Gf, UsdGeom, UsdSkel, Vt

        self._Gf, self._Vt, self._UsdGeom = Gf, Vt, UsdGeom
        self.rig = rig
        self.to_stage = np.asarray(to_stage, np.float64)
        self.n_expr = len(rig.names)
        names = [_token(n) for n in rig.names] + list(JAW_SHAPE_NAMES)
        if len(set(names)) != len(names):
            raise ValueError(f"expression names collide as USD names: {names}")
        self.shape_names = names
        skel_root = UsdSkel.Root.Define(stage, root)
        skel = UsdSkel.Skeleton.Define(stage, f"{root}/{SKELETON}")
        skel.CreateJointsAttr([JOINT])
        skel.CreateJointNamesAttr([JOINT])
        eye = Gf.Matrix4d(1.0)
        skel.CreateBindTransformsAttr(Vt.Matrix4dArray([eye]))
        skel.CreateRestTransformsAttr(Vt.Matrix4dArray([eye]))
        anim = UsdSkel.Animation.Define(stage, f"{root}/{ANIMATION}")
        anim.CreateJointsAttr([JOINT])
        anim.CreateBlendShapesAttr(names)
        anim.CreateScalesAttr().Set(Vt.Vec3hArray([Gf.Vec3h(1.0, 1.0, 1.0)]))
        self._translations = anim.CreateTranslationsAttr()
        self._rotations = anim.CreateRotationsAttr()
        self._weights = anim.CreateBlendShapeWeightsAttr()
        UsdSkel.BindingAPI.Apply(skel.GetPrim()).CreateAnimationSourceRel().SetTargets([anim.GetPath()])

        mesh = UsdGeom.Mesh.Define(stage, f"{root}/{FACE}")
        f = np.asarray(faces, np.int32)
        mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(f), 3, np.int32)))
        mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(f.ravel())))
        mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        mesh.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
        rest = np.asarray(rig.neutral, np.float32)
        mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(rest))
        mesh.CreateExtentAttr(Vt.Vec3fArray.FromNumpy(np.stack([rest.min(0) - 50, rest.max(0) + 50])))
        binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
        binding.CreateSkeletonRel().SetTargets([skel.GetPath()])
        binding.CreateJointIndicesPrimvar(constant=True, elementSize=1).Set(Vt.IntArray([0]))
        binding.CreateJointWeightsPrimvar(constant=True, elementSize=1).Set(Vt.FloatArray([1.0]))
        binding.CreateGeomBindTransformAttr(eye)
        shapes = np.concatenate([np.asarray(rig.expressions, np.float64), jaw_shapes(rig)], 0)
        targets = []
        for name, offsets in zip(names, shapes):
            bs = UsdSkel.BlendShape.Define(stage, f"{root}/{FACE}/{name}")
            used = np.flatnonzero(np.abs(offsets).max(1) > 0)
            bs.CreateOffsetsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(offsets[used], np.float32)))
            if len(used) < len(offsets):
                bs.CreatePointIndicesAttr(Vt.IntArray.FromNumpy(used.astype(np.int32)))
            targets.append(bs.GetPath())
        binding.CreateBlendShapesAttr(names)
        binding.CreateBlendShapeTargetsRel().SetTargets(targets)
        self._visibility = skel_root.CreateVisibilityAttr()
        self._visible: bool | None = None
        self.samples = 0

    def weights(self, fit) -> np.ndarray | None:
        """``(E + 12,)`` the frame's blend-shape weights (None when the frame has no fit)."""
        if getattr(fit, "status", "fitted") == "skipped" or getattr(fit, "head_R", None) is None:
            return None
        b = frame_base_weights(fit, self.n_expr)
        w = np.concatenate([b, jaw_weights(fit.jaw_R, fit.jaw_t)])
        return w if np.isfinite(w).all() and np.isfinite(np.asarray(fit.head_R)).all() else None

    def write(self, fit) -> None:
        """Add the samples of one frame (time code = ``fit.frame``)."""
        from pxr import Usd

        Gf, Vt = self._Gf, self._Vt
        t = Usd.TimeCode(int(fit.frame))
        w = self.weights(fit)
        visible = w is not None
        if visible != self._visible:
            tok = self._UsdGeom.Tokens.inherited if visible else self._UsdGeom.Tokens.invisible
            self._visibility.Set(tok, t)
            self._visible = visible
        if not visible:
            return
        q, tr = head_joint_transform(fit.head_R, fit.head_t, self.to_stage)
        self._rotations.Set(Vt.QuatfArray([Gf.Quatf(float(q[0]), Gf.Vec3f(*(float(v) for v in q[1:])))]), t)
        self._translations.Set(Vt.Vec3fArray([Gf.Vec3f(*(float(v) for v in tr))]), t)
        self._weights.Set(Vt.FloatArray.FromNumpy(w.astype(np.float32)), t)
        self.samples += 1

    def release(self) -> None:
        for name in ("_translations", "_rotations", "_weights", "_visibility"):
            if hasattr(self, name):
                delattr(self, name)
