"""Animation curves ``curves.csv`` (``--formats curves``): one row per frame, Live Link Face's layout first.

Columns, in this order (comma-separated, header row, one row per exported frame):

1. The 63 columns of a Live Link Face CSV take, so that Live Link Face / ARKit-curve importers (Unreal's
   LiveLinkFaceImporter, Blender and Maya CSV importers, which read by name or by position):
   ``Timecode`` (``HH:MM:SS:FF.fff``, frame ``FF`` counted at the nominal rate ``round(fps)``, ``.fff``
   the sub-frame: 0 here; frame 0 of the video is ``00:00:00:00.000``), ``BlendShapeCount`` (61), the 52
   ARKit curves in Live Link Face's order and spelling (``EyeBlinkLeft`` ... ``TongueOut``; ``Left`` is
   the actor's left, as in ARKit), ``HeadYaw``, ``HeadPitch``, ``HeadRoll`` (radians) and the six eye
   rotations (0: not solved).
   An ARKit curve takes the base weight of the actor's shape of that name (``jawOpen``; ``mouthSmile_L``
   for ``MouthSmileLeft``); one the actor has only as ``_L``/``_R`` halves (``browInnerUp``) takes their
   mean; one the actor has not is 0.
2. ``Frame`` (index in the video), ``TimeS``, ``Status`` (fitted / bridged / skipped).
3. The head translation ``HeadTxMm, HeadTyMm, HeadTzMm`` (camera frame, OpenCV axes, mm), the jaw
   rotation ``JawYaw, JawPitch, JawRoll`` (radians, head frame; an opening jaw has a negative pitch) and
   translation ``JawTxMm, JawTyMm, JawTzMm``.
4. One column per expression of the actor under its own name (``jawOpen``, ``mouthSmile_L``, ...):
   the per-frame base weights ``b_i`` exactly as the fit solved them.

Head angles follow :func:`capture.export.rig.head_angles_deg` (yaw toward the actor's left, pitch up,
relative to a frontal view). The weights are the fit's per-frame *base* (:mod:`capture.export.rig`):
the spatially varying local detail of the fit is in the meshes, not in the curves. A frame without a fit
(``skipped``) repeats the previous frame's values (zeros before the first fit) so that importers get
continuous curves; its ``Status`` says so.
"""

from __future__ import annotations

import csv
import io
from pathlib import Path

import numpy as np

from capture.export.base import ExportContext, FrameFitLike, PendingFile
from capture.export.rig import FaceRig, frame_base_weights, head_angles_deg, jaw_angles_deg

CURVES_FILE = "curves.csv"

#: The 52 ARKit blend shapes in Live Link Face's CSV order and spelling.
LIVE_LINK_FACE_SHAPES = (
    "EyeBlinkLeft", "EyeLookDownLeft", "EyeLookInLeft", "EyeLookOutLeft", "EyeLookUpLeft", "EyeSquintLeft",
    "EyeWideLeft", "EyeBlinkRight", "EyeLookDownRight", "EyeLookInRight", "EyeLookOutRight", "EyeLookUpRight",
    "EyeSquintRight", "EyeWideRight", "JawForward", "JawRight", "JawLeft", "JawOpen", "MouthClose",
    "MouthFunnel", "MouthPucker", "MouthRight", "MouthLeft", "MouthSmileLeft", "MouthSmileRight",
    "MouthFrownLeft", "MouthFrownRight", "MouthDimpleLeft", "MouthDimpleRight", "MouthStretchLeft",
    "MouthStretchRight", "MouthRollLower", "MouthRollUpper", "MouthShrugLower", "MouthShrugUpper",
    "MouthPressLeft", "MouthPressRight", "MouthLowerDownLeft", "MouthLowerDownRight", "MouthUpperUpLeft",
    "MouthUpperUpRight", "BrowDownLeft", "BrowDownRight", "BrowInnerUp", "BrowOuterUpLeft", "BrowOuterUpRight",
    "CheekPuff", "CheekSquintLeft", "CheekSquintRight", "NoseSneerLeft", "NoseSneerRight", "TongueOut")
LIVE_LINK_FACE_POSE = ("HeadYaw", "HeadPitch", "HeadRoll", "LeftEyeYaw", "LeftEyePitch", "LeftEyeRoll",
                       "RightEyeYaw", "RightEyePitch", "RightEyeRoll")
LIVE_LINK_FACE_HEADER = ("Timecode", "BlendShapeCount") + LIVE_LINK_FACE_SHAPES + LIVE_LINK_FACE_POSE
EXTRA_HEADER = ("Frame", "TimeS", "Status", "HeadTxMm", "HeadTyMm", "HeadTzMm", "JawYaw", "JawPitch", "JawRoll",
                "JawTxMm", "JawTyMm", "JawTzMm")


def _arkit_key(name: str) -> str:
    """``mouthSmile_L`` / ``MouthSmileLeft`` / ``mouthSmileLeft`` -> ``mouthsmileleft`` (for matching)."""
    n = name.strip()
    if n.endswith(("_L", "_l")):
        n = n[:-2] + "Left"
    elif n.endswith(("_R", "_r")):
        n = n[:-2] + "Right"
    return n.replace("_", "").lower()


def arkit_mapping(names: tuple[str, ...] | list[str]) -> dict[str, list[int]]:
    """For each Live Link Face shape column, the actor expressions (indices) whose mean it takes."""
    keys = {_arkit_key(n): i for i, n in enumerate(names)}
    out: dict[str, list[int]] = {}
    for col in LIVE_LINK_FACE_SHAPES:
        k = col.lower()
        if k in keys:
            out[col] = [keys[k]]
        elif k + "left" in keys and k + "right" in keys:
            out[col] = [keys[k + "left"], keys[k + "right"]]
    return out


def timecode(frame: int, fps: float) -> str:
    """``HH:MM:SS:FF.fff`` of a frame index at the nominal integer rate ``round(fps)`` (non-drop)."""
    rate = max(1, int(round(fps)))
    f = int(frame)
    secs, ff = divmod(f, rate)
    hh, rem = divmod(secs, 3600)
    mm, ss = divmod(rem, 60)
    return f"{hh:02d}:{mm:02d}:{ss:02d}:{ff:02d}.000"


class CurvesWriter:
    """Accumulates one row per frame (small: ~100 numbers) and writes ``curves.csv`` atomically on close."""

    needs_image = False

    def __init__(self, out_dir: Path, ctx: ExportContext):
        rig = getattr(ctx, "rig", None)
        if not isinstance(rig, FaceRig):
            raise ValueError("the curves export needs the actor's rig (ExportContext.rig, a FaceRig)")
        self.out_dir, self.ctx, self.rig = Path(out_dir), ctx, rig
        self.names = tuple(rig.names)
        self.mapping = arkit_mapping(self.names)
        self.header = LIVE_LINK_FACE_HEADER + EXTRA_HEADER + self.names
        if len(set(self.header)) != len(self.header):
            dup = sorted({h for h in self.header if self.header.count(h) > 1})
            raise ValueError(f"actor expression names collide with curves.csv columns: {dup}")
        self.rows: list[list] = []
        self._held: np.ndarray | None = None
        self._last: int | None = None

    def values(self, fit: FrameFitLike) -> np.ndarray | None:
        """The numeric part of a frame's row (base weights, head, jaw); None when the frame has no fit."""
        E = len(self.names)
        if getattr(fit, "status", "fitted") == "skipped" or getattr(fit, "head_R", None) is None:
            return None
        b = frame_base_weights(fit, E)
        head = np.deg2rad(head_angles_deg(fit.head_R))
        jaw = np.deg2rad(jaw_angles_deg(fit.jaw_R))
        v = np.concatenate([b, head, np.asarray(fit.head_t, np.float64).reshape(3), jaw,
                            np.asarray(fit.jaw_t, np.float64).reshape(3)])
        return v if np.isfinite(v).all() else None

    def write(self, fit: FrameFitLike, image=None, detection=None) -> None:
        frame = int(fit.frame)
        if self._last is not None and frame <= self._last:
            raise ValueError(f"frames must arrive in increasing order: {frame} after {self._last}")
        self._last = frame
        E = len(self.names)
        v = self.values(fit)
        status = getattr(fit, "status", "fitted")
        if v is None:
            status = "skipped"
            v = self._held if self._held is not None else np.zeros(E + 12)
        self._held = v
        b, head, head_t, jaw, jaw_t = v[:E], v[E:E + 3], v[E + 3:E + 6], v[E + 6:E + 9], v[E + 9:E + 12]
        arkit = [float(np.mean(b[self.mapping[c]])) if c in self.mapping else 0.0 for c in LIVE_LINK_FACE_SHAPES]
        row = [timecode(frame, self.ctx.fps), len(LIVE_LINK_FACE_SHAPES) + len(LIVE_LINK_FACE_POSE)]
        row += arkit + [head[0], head[1], head[2]] + [0.0] * 6
        row += [frame, frame / float(self.ctx.fps), status] + list(head_t) + list(jaw) + list(jaw_t) + list(b)
        self.rows.append(row)

    def text(self) -> str:
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(self.header)
        for r in self.rows:
            w.writerow([f"{x:.6g}" if isinstance(x, float) else x for x in r])
        return buf.getvalue()

    def close(self) -> list[Path]:
        pending = PendingFile(self.out_dir / CURVES_FILE)
        try:
            pending.tmp.write_text(self.text(), encoding="utf-8")
            return [pending.commit()]
        except BaseException:
            pending.discard()
            raise

    def abort(self) -> None:
        """Nothing is on disk before close."""
