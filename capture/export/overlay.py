"""Quality-control video ``overlay.mp4``: the fit drawn over every exported frame.

Drawn on each video frame (BGR in, H.264 ``yuv420p`` MP4 out at the video's frame rate):

* the projected fitted mesh in orange: front-facing triangle edges (``wireframe``, the default) or
  the vertices (``dots``), blended at 50 % so the face stays visible. Vertices are projected through
  the camera including its distortion (``cv2.projectPoints`` with the OpenCV K and dist, camera
  frame points, identity pose); triangles behind the camera or facing away are not drawn;
* the fitted landmarks (the mesh's, projected) as small orange dots;
* the detected landmarks in green, the radius growing with the confidence (1 px at 0 to 4 px at 1;
  3 px when the detector gives none);
* one text line: frame index, reprojection RMS in pixels, fit status (and "no face" when the
  detector found none).

Frames are encoded as they arrive (nothing is held), into a temporary sibling that ``close()``
renames over ``overlay.mp4``; ``abort()`` deletes it. Odd frame sizes are padded by one pixel on the
right/bottom (yuv420p needs even sizes); pixel coordinates are unchanged. Rewritten whole by every
export run.
"""

from __future__ import annotations

from fractions import Fraction
from pathlib import Path

import numpy as np

from capture.io.errors import CaptureError
from capture.export.base import ExportContext, FrameFitLike, PendingFile, check_vertices

OVERLAY_FILE = "overlay.mp4"
DETECTED_BGR = (80, 220, 60)      # green
MESH_BGR = (0, 140, 255)          # orange
MESH_ALPHA = 0.5
_SHIFT = 4                        # sub-pixel drawing: coordinates * 2**4


def _av():
    try:
        import av
    except ImportError:  # pragma: no cover - depends on the environment
        raise CaptureError("the overlay export needs PyAV: pip install av") from None
    return av


def unique_edges(faces: np.ndarray) -> np.ndarray:
    """(F, 3) triangles -> (E, 2) undirected edges, each once, plus (F, 3) edge ids per face."""
    f = np.asarray(faces, np.int64)
    e = np.stack([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]], 1).reshape(-1, 2)
    e.sort(axis=1)
    edges, inverse = np.unique(e, axis=0, return_inverse=True)
    return edges, inverse.reshape(-1, 3)


def project(vertices: np.ndarray, camera) -> np.ndarray:
    """(V, 3) camera-frame mm -> (V, 2) pixels through K and the OpenCV distortion of ``camera``."""
    import cv2

    K = np.asarray(camera.K, np.float64)
    dist = np.asarray(getattr(camera, "dist", ()), np.float64).reshape(-1)
    pts, _ = cv2.projectPoints(np.asarray(vertices, np.float64).reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K,
                               dist if dist.size else None)
    return pts.reshape(-1, 2)


class OverlayWriter:
    """Draws each frame's fit and detections and encodes it with PyAV (libx264, yuv420p)."""

    needs_image = True

    def __init__(self, out_dir: Path, ctx: ExportContext):
        av = _av()
        self.ctx = ctx
        self.size = ctx.image_size
        self.enc_size = (self.size[0] + self.size[0] % 2, self.size[1] + self.size[1] % 2)
        self._edges, self._face_edges = unique_edges(ctx.faces)
        self._file = PendingFile(Path(out_dir) / OVERLAY_FILE)
        self._av = av
        try:
            self._container = av.open(str(self._file.tmp), mode="w", format="mp4",
                                      options={"movflags": "+faststart"})
            self._stream = self._container.add_stream("libx264", rate=Fraction(ctx.fps).limit_denominator(1001))
            self._stream.width, self._stream.height = self.enc_size
            self._stream.pix_fmt = "yuv420p"
            self._stream.options = {"crf": str(int(ctx.options.overlay_crf)), "preset": "veryfast"}
        except Exception:
            self._close_container()
            self._file.discard()
            raise
        self._vertex_count: int | None = None
        self.frames = 0

    # -- drawing ------------------------------------------------------------------------------
    def draw(self, fit: FrameFitLike, image: np.ndarray, detection=None) -> np.ndarray:
        """The overlay of one frame (BGR uint8 of the video's size)."""
        import cv2

        w, h = self.size
        img = np.asarray(image)
        if img.shape != (h, w, 3) or img.dtype != np.uint8:
            raise ValueError(f"frame {fit.frame}: image expected uint8 ({h}, {w}, 3), got {img.dtype} {img.shape}")
        out = img.copy()
        scale = 1 << _SHIFT
        v = check_vertices(fit, self.ctx, self._vertex_count)
        if v is not None:
            self._vertex_count = v.shape[0]
            layer = out.copy()
            px = project(v, self.ctx.camera)
            ok = np.isfinite(px).all(1) & (v[:, 2] > 1e-3) & (np.abs(px) < 1e5).all(1)
            if self.ctx.options.overlay_mesh == "dots":
                for x, y in np.round(px[ok] * scale).astype(np.int64):
                    cv2.circle(layer, (int(x), int(y)), scale, MESH_BGR, -1, cv2.LINE_AA, _SHIFT)
            else:
                f = self.ctx.faces
                tri = v[f].astype(np.float64)
                normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
                front = (np.einsum("ij,ij->i", normal, tri.mean(1)) < 0) & ok[f].all(1)
                eids = np.unique(self._face_edges[front])
                segs = np.round(px[self._edges[eids]] * scale).astype(np.int32)
                if len(segs):
                    cv2.polylines(layer, list(segs), False, MESH_BGR, 1, cv2.LINE_AA, _SHIFT)
            cv2.addWeighted(layer, MESH_ALPHA, out, 1 - MESH_ALPHA, 0, dst=out)
        fit_lm = getattr(fit, "landmarks_fit", None)
        if fit_lm is not None and getattr(fit, "status", "fitted") != "skipped":
            for x, y in np.asarray(fit_lm, np.float64).reshape(-1, 2):
                if np.isfinite(x) and np.isfinite(y):
                    cv2.circle(out, (int(round(x * scale)), int(round(y * scale))), scale, MESH_BGR, -1,
                               cv2.LINE_AA, _SHIFT)
        note = ""
        if detection is not None:
            pts = np.asarray(detection.points, np.float64).reshape(-1, 2)
            conf = getattr(detection, "confidence", None)
            radii = np.full(len(pts), 3.0) if conf is None else 1.0 + 3.0 * np.clip(
                np.nan_to_num(np.asarray(conf, np.float64), nan=0.0), 0.0, 1.0)
            for (x, y), r in zip(pts, radii):
                if np.isfinite(x) and np.isfinite(y):
                    cv2.circle(out, (int(round(x * scale)), int(round(y * scale))), int(round(r * scale)),
                               DETECTED_BGR, -1, cv2.LINE_AA, _SHIFT)
            if not detection.face_found:
                note = "  no face"
        rms = getattr(fit, "reprojection_rms_px", None)
        rms_text = "-" if rms is None or not np.isfinite(rms) else f"{rms:.2f} px"
        text = f"frame {int(fit.frame)}  rms {rms_text}  {getattr(fit, 'status', 'fitted')}{note}"
        fs = max(0.4, h / 720 * 0.6)
        org = (int(8 * fs / 0.6), int(24 * fs / 0.6))
        cv2.putText(out, text, org, cv2.FONT_HERSHEY_SIMPLEX, fs, (0, 0, 0), 3, cv2.LINE_AA)
        cv2.putText(out, text, org, cv2.FONT_HERSHEY_SIMPLEX, fs, (255, 255, 255), 1, cv2.LINE_AA)
        return out

    # -- writer API ---------------------------------------------------------------------------
    def write(self, fit: FrameFitLike, image: np.ndarray | None = None, detection=None) -> None:
        if image is None:
            raise ValueError(f"frame {fit.frame}: the overlay export needs the video frame (image is None)")
        out = self.draw(fit, image, detection)
        if self.enc_size != self.size:
            out = np.pad(out, ((0, self.enc_size[1] - self.size[1]), (0, self.enc_size[0] - self.size[0]), (0, 0)))
        frame = self._av.VideoFrame.from_ndarray(np.ascontiguousarray(out), format="bgr24")
        for packet in self._stream.encode(frame):
            self._container.mux(packet)
        self.frames += 1

    def close(self) -> list[Path]:
        try:
            for packet in self._stream.encode():
                self._container.mux(packet)
            self._container.close()
            self._container = None
            return [self._file.commit()]
        except BaseException:
            self.abort()
            raise

    def abort(self) -> None:
        self._close_container()
        self._file.discard()

    def _close_container(self) -> None:
        c = getattr(self, "_container", None)
        self._container = None
        if c is not None:
            try:
                c.close()
            except Exception:
                pass
