"""The take as one USD file: ``take.usdc`` (or ``take.usda``) with time-sampled mesh points.

Axes -- the project's one conversion to USD's convention (stated here and nowhere else):
    Our camera frame is OpenCV's (x right, y down, z forward). USD's convention is y up with a
    camera looking down -z (OpenGL). Points are written as ``p_usd = CAMERA_TO_USD @ p_cam`` with
    ``CAMERA_TO_USD = diag(1, -1, -1)``, a rotation of 180 degrees about x (determinant +1, so
    triangle winding and handedness are unchanged). The stage's ``upAxis`` is ``Y``; the video's
    camera sits at the origin looking down -z, so a default USD camera there sees what the video saw.

Units and time:
    ``metersPerUnit = 0.001`` (millimetres). ``timeCodesPerSecond = framesPerSecond = fps`` and the
    time code of a frame is its index in the video, so ``time_s = frame / fps``;
    ``startTimeCode``/``endTimeCode`` are the first and last exported frame.

Scene:
    ``/Take`` (Xform, the default prim) holds ``/Take/Face`` (Mesh): topology (``faceVertexCounts``,
    ``faceVertexIndices``, ``subdivisionScheme = none``) written once; ``points`` and ``extent``
    with one time sample per frame that has a mesh. A frame without a mesh (``skipped``) gets no
    points sample and the mesh's ``visibility`` is time-sampled ``invisible`` there (``inherited``
    again at the next meshed frame). ``customLayerData`` records the conventions and the source.

Writing:
    The crate is created at a temporary sibling of the target. Frames are buffered and written in
    bulk every ``ExportOptions.usd_save_every`` frames: the block's points are converted to USD axes in
    one product and authored as time samples straight into the layer inside one ``Sdf.ChangeBlock``,
    then the crate is saved; a crate save appends the new samples to the file and lets go of them in
    memory, so memory stays flat however long the take (one block of points is held). ``close()`` saves and
    renames the file over the target (``.usda``: the crate is exported to text first). USD is
    rewritten whole by every export run (cheap next to the fit).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from capture.io.errors import CaptureError
from capture.export.base import ExportContext, FrameFitLike, PendingFile, check_vertices
from capture.io.threads import limit_usd_pool

#: OpenCV camera frame (x right, y down, z forward) -> USD (y up, camera looking down -z).
#: Column-vector form: p_usd = CAMERA_TO_USD @ p_cam. A 180-degree rotation about x.
CAMERA_TO_USD = np.diag([1.0, -1.0, -1.0])
UP_AXIS = "Y"
METERS_PER_UNIT = 0.001
MESH_PRIM = "/Take/Face"


_CAMERA_TO_USD_SIGNS = np.diag(CAMERA_TO_USD).astype(np.float32)
assert np.array_equal(np.diag(_CAMERA_TO_USD_SIGNS), CAMERA_TO_USD), "CAMERA_TO_USD is a diagonal of signs"


def camera_to_usd(points: np.ndarray) -> np.ndarray:
    """(..., 3) camera-frame points -> USD stage points (float32), see :data:`CAMERA_TO_USD`.

    The rotation is a diagonal of signs, so the product is a per-axis sign flip (exact in float32)."""
    return np.asarray(points, np.float32) * _CAMERA_TO_USD_SIGNS


def _pxr():
    try:
        from pxr import Sdf, Usd, UsdGeom, Vt
    except ImportError:  # pragma: no cover - depends on the environment
        raise CaptureError("the usd export needs Pixar's USD: pip install usd-core") from None
    limit_usd_pool()        # the run's threads, not a pool of USD's own (capture.io.threads)
    return Sdf, Usd, UsdGeom, Vt


class UsdTakeWriter:
    """Streams mesh points into one USD layer, saved incrementally, renamed into place on close."""

    needs_image = False

    def __init__(self, out_dir: Path, ctx: ExportContext):
        Sdf, Usd, UsdGeom, Vt = _pxr()
        self._Sdf, self._Usd, self._UsdGeom, self._Vt = Sdf, Usd, UsdGeom, Vt
        self.ctx = ctx
        self.ascii = ctx.options.usd_ascii
        self.target = Path(out_dir) / ("take.usda" if self.ascii else "take.usdc")
        self._crate = PendingFile(self.target.with_suffix(".usdc"))   # the crate being streamed
        try:
            self._layer = Sdf.Layer.CreateNew(str(self._crate.tmp))
            stage = Usd.Stage.Open(self._layer)
            UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
            UsdGeom.SetStageMetersPerUnit(stage, METERS_PER_UNIT)
            stage.SetTimeCodesPerSecond(float(ctx.fps))
            stage.SetFramesPerSecond(float(ctx.fps))
            root = UsdGeom.Xform.Define(stage, "/Take")
            stage.SetDefaultPrim(root.GetPrim())
            mesh = UsdGeom.Mesh.Define(stage, MESH_PRIM)
            faces = ctx.faces.astype(np.int32)
            mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(faces), 3, np.int32)))
            mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(faces.ravel())))
            mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
            mesh.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
            self._points_path = mesh.CreatePointsAttr().GetPath()
            self._extent_path = mesh.CreateExtentAttr().GetPath()
            self._visibility = mesh.CreateVisibilityAttr()
            self._layer.customLayerData = {
                "capture:units": "mm (metersPerUnit 0.001)",
                "capture:axes": "points = diag(1,-1,-1) @ OpenCV camera frame (x right, y down, z forward); "
                                "up axis Y, the video camera at the origin looking down -z",
                "capture:timeCode": "frame index in the video; time_s = timeCode / timeCodesPerSecond",
                "capture:source": ctx.source,
            }
            self._stage = stage
            self._rig = None
            if getattr(ctx, "rig", None) is not None:   # --formats curves: the UsdSkel rig beside the mesh
                from capture.export.usd_skel import SkelRigWriter

                self._rig = SkelRigWriter(stage, ctx.rig, ctx.faces, CAMERA_TO_USD)
        except Exception:
            self._release()
            self._crate.discard()
            raise
        self._first: int | None = None
        self._last: int | None = None
        self._visible: bool | None = None
        self._vertex_count: int | None = None
        self._since_save = 0
        self._pending: list[tuple[int, np.ndarray]] = []   # (frame, camera-frame vertices) not yet authored
        self.samples = 0

    def write(self, fit: FrameFitLike, image=None, detection=None) -> None:
        frame = int(fit.frame)
        if self._last is not None and frame <= self._last:
            raise ValueError(f"frames must arrive in increasing order: {frame} after {self._last}")
        v = check_vertices(fit, self.ctx, self._vertex_count)
        visible = v is not None
        if visible != self._visible:
            self._visibility.Set(self._UsdGeom.Tokens.inherited if visible else self._UsdGeom.Tokens.invisible,
                                 self._Usd.TimeCode(frame))
            self._visible = visible
        if visible:
            self._vertex_count = v.shape[0]
            self._pending.append((frame, v))
            self.samples += 1
        if self._rig is not None:
            self._rig.write(fit)
        if self._first is None:
            self._first = frame
        self._last = frame
        self._since_save += 1
        if self._since_save >= self.ctx.options.usd_save_every:
            self._flush()

    def _flush(self) -> None:
        """Author the buffered frames' points and extents in one change block, then save the crate.

        The points of the block are converted to USD axes in one product; the samples go straight into
        the layer (``Sdf.Layer.SetTimeSample``), and the save appends them to the file and lets go of them.
        """
        Sdf, Vt = self._Sdf, self._Vt
        if self._pending:
            frames = [f for f, _ in self._pending]
            pts = camera_to_usd(np.stack([v for _, v in self._pending]))          # (B, V, 3) float32
            axes = np.ascontiguousarray(pts.transpose(0, 2, 1))                     # (B, 3, V): 20x faster min/max
            lo, hi = axes.min(2), axes.max(2)
            self._pending = []
            with Sdf.ChangeBlock():
                for b, f in enumerate(frames):
                    self._layer.SetTimeSample(self._points_path, float(f), Vt.Vec3fArray.FromNumpy(pts[b]))
                    self._layer.SetTimeSample(self._extent_path, float(f),
                                              Vt.Vec3fArray.FromNumpy(np.stack([lo[b], hi[b]])))
        self._layer.Save()
        self._since_save = 0

    def close(self) -> list[Path]:
        try:
            if self._first is not None:
                self._stage.SetStartTimeCode(self._first)
                self._stage.SetEndTimeCode(self._last)
            self._flush()
            if self.ascii:
                text = PendingFile(self.target)
                try:
                    if not self._layer.Export(str(text.tmp)):
                        raise OSError(f"USD could not export {text.tmp}")
                    self._release()
                    text.commit()
                except BaseException:
                    text.discard()
                    raise
                self._crate.discard()
            else:
                self._release()
                self._crate.commit()
        except BaseException:
            self.abort()
            raise
        return [self.target]

    def abort(self) -> None:
        self._release()
        self._crate.discard()

    def _release(self) -> None:
        """Drop every reference to the layer so USD lets go of the (temporary) file."""
        self._pending = []
        if getattr(self, "_rig", None) is not None:
            self._rig.release()
        for name in ("_visibility", "_rig", "_stage", "_layer"):
            if hasattr(self, name):
                delattr(self, name)
