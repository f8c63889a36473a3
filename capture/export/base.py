"""What every exporter shares: the frame interfaces it reads, the take context, options, checks.

Exporters are duck-typed against two tiny protocols so that they do not import the fitter:

* :class:`FrameFitLike` -- one fitted frame (``capture.fit.take.FrameFit``).
* :class:`DetectionLike` -- the detected landmarks of that frame
  (``capture.detector.runtime.FrameLandmarks``), passed beside it.

Conventions (the project's, see ``DESIGN.md``): lengths in millimetres; the camera frame is
OpenCV's (x right, y down, z forward); ``x_cam = head_R @ x_head + head_t``; pixels with centres at
integer coordinates. The single conversion to a foreign convention (USD's y-up camera) lives in
:mod:`capture.export.usd`.

Every file goes to disk through :mod:`capture.io.atomic`: per-frame files with
:func:`capture.io.atomic.write_bytes`, take-long files (USD, MP4, NPZ) through a
:class:`PendingFile` -- a temporary sibling held open for the whole take and renamed over the
target by ``close()`` (``abort()`` deletes it and leaves earlier outputs alone).
"""

from __future__ import annotations

import contextlib
import os
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np

from capture.io.atomic import atomic_path

#: Per-frame fit status, stored in NPZ files as int8 codes (index into this tuple).
STATUSES = ("fitted", "bridged", "skipped")
#: Layers the overlay can draw (``capture run --overlay``): the shaded fitted mesh, its triangle edges,
#: its silhouette and feature contours (lids, lips, brows), the landmarks with their residuals, the header.
OVERLAY_LAYERS = ("mesh", "wireframe", "contours", "landmarks", "header")
DEFAULT_OVERLAY = ("mesh", "contours", "landmarks", "header")
#: Where mesh vertices are expressed: OpenCV camera frame, or the actor's template (head) frame.
MESH_FRAMES = ("camera", "head")


@runtime_checkable
class DetectionLike(Protocol):
    """Detected landmarks of one frame (full-frame pixels, OpenCV pixel centres)."""

    points: np.ndarray                 # (L, 2) px; NaN when no face
    confidence: np.ndarray | None      # (L,) in 0..1, or None when the detector gives none
    face_found: bool


@runtime_checkable
class FrameFitLike(Protocol):
    """One fitted frame; fields may be ``None`` on a ``skipped`` frame (no face, not fitted)."""

    frame: int                         # index of the frame in the video
    head_R: np.ndarray                 # (3, 3) x_cam = head_R @ x_head + head_t
    head_t: np.ndarray                 # (3,) mm
    jaw_R: np.ndarray                  # (3, 3) jaw transform in the head frame
    jaw_t: np.ndarray                  # (3,) mm
    code: np.ndarray                   # (f,) frame code
    coefficients_landmarks: np.ndarray  # (L, E) expression coefficients at the landmarks
    vertices: np.ndarray               # (V, 3) float32 mm, camera frame
    landmarks_fit: np.ndarray          # (L, 2) px, the fitted mesh's landmarks projected
    reprojection_rms_px: float
    status: str                        # "fitted" | "bridged" | "skipped"


@dataclass(frozen=True)
class ExportOptions:
    """Settings of the exporters (all have defaults; the run's report should record them).

    Attributes:
        overwrite: rewrite per-frame mesh files that already exist (default: keep them, so a rerun
            of an export only writes the missing frames). Take-long files are always rewritten.
        mesh_frame: ``camera`` (OpenCV camera frame, the default) or ``head`` (the actor's template
            frame: ``x_head = head_R.T @ (x_cam - head_t)``, the head's rigid motion removed) for
            OBJ/PLY. USD is always in the camera frame (converted to USD's y-up axes).
        usd_ascii: write ``take.usda`` (text) instead of ``take.usdc`` (binary crate).
        usd_save_every: frames between incremental saves of the USD crate (bounds memory).
        overlay_crf: H.264 constant-quality factor of the overlay video (lower is better).
        overlay_layers: what the overlay draws, any of :data:`OVERLAY_LAYERS` (default
            :data:`DEFAULT_OVERLAY`: shaded mesh, contours, landmarks, header).
    """

    overwrite: bool = False
    mesh_frame: str = "camera"
    usd_ascii: bool = False
    usd_save_every: int = 32
    overlay_crf: int = 23
    overlay_layers: tuple[str, ...] = DEFAULT_OVERLAY

    def __post_init__(self) -> None:
        if self.mesh_frame not in MESH_FRAMES:
            raise ValueError(f"mesh_frame must be one of {MESH_FRAMES}, got {self.mesh_frame!r}")
        unknown = [x for x in self.overlay_layers if x not in OVERLAY_LAYERS]
        if unknown or isinstance(self.overlay_layers, str):
            raise ValueError(f"overlay_layers must be a tuple of {OVERLAY_LAYERS}, got {self.overlay_layers!r}")
        if self.usd_save_every < 1:
            raise ValueError(f"usd_save_every must be >= 1, got {self.usd_save_every}")
        if not 0 <= self.overlay_crf <= 51:
            raise ValueError(f"overlay_crf must be in 0..51, got {self.overlay_crf}")

    def to_dict(self) -> dict:
        """Plain JSON data (tuples as lists): what an export's key and report record."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in self.__dict__.items()}


@dataclass
class ExportContext:
    """What the exporters know about the take before the first frame.

    Attributes:
        faces: (F, 3) triangle vertex indices of the actor's template (``template.ply``).
        fps: frame rate of the video (frames per second).
        image_size: (width, height) of the video frames in pixels.
        camera: the camera (``calib.camera.Camera`` or anything with ``K`` (3, 3) and ``dist``).
        frame_count: number of frames the run will export (a hint, for progress and preallocation).
        options: :class:`ExportOptions`.
        source: one line saying where the take came from (written into file headers).
        rig: the actor as a blend-shape rig (:class:`capture.export.rig.FaceRig`) for ``curves`` and the
            UsdSkel animation in ``take.usdc``; None when neither is exported.
        features: the template's feature lines for the overlay's contours
            (:class:`capture.export.features.FaceFeatures`); None: the boundary loops of ``faces`` only.
    """

    faces: np.ndarray
    fps: float
    image_size: tuple[int, int]
    camera: Any
    frame_count: int = 0
    options: ExportOptions = field(default_factory=ExportOptions)
    source: str = ""
    rig: Any = None
    features: Any = None

    def __post_init__(self) -> None:
        faces = np.asarray(self.faces)
        if faces.ndim != 2 or faces.shape[1] != 3 or faces.size == 0:
            raise ValueError(f"faces: expected (F, 3), got {faces.shape}")
        if not np.issubdtype(faces.dtype, np.integer) or faces.min() < 0:
            raise ValueError("faces must be non-negative integer vertex indices")
        self.faces = faces.astype(np.int64)
        if not (self.fps > 0 and np.isfinite(self.fps)):
            raise ValueError(f"fps must be positive, got {self.fps}")
        w, h = (int(v) for v in self.image_size)
        if w <= 0 or h <= 0:
            raise ValueError(f"image_size must be (width, height) > 0, got {self.image_size}")
        self.image_size = (w, h)

    @cached_property
    def min_vertex_count(self) -> int:
        """The smallest vertex count the faces allow (one more than the largest index; checked per frame)."""
        return int(self.faces.max()) + 1


def check_vertices(fit: FrameFitLike, ctx: ExportContext, expected: int | None) -> np.ndarray | None:
    """The frame's vertices as float32 (V, 3), or ``None`` when the frame has none to export.

    A ``skipped`` frame, a missing array or non-finite coordinates mean "no mesh for this frame".
    Raises ValueError (naming expected and actual shapes) when the shape disagrees with the faces
    or with the vertex count of earlier frames (``expected``).
    """
    v = getattr(fit, "vertices", None)
    if v is None or getattr(fit, "status", "fitted") == "skipped":
        return None
    v = np.asarray(v, dtype=np.float32)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"frame {fit.frame}: vertices expected (V, 3), got {v.shape}")
    if expected is not None and v.shape[0] != expected:
        raise ValueError(f"frame {fit.frame}: vertices expected ({expected}, 3) like earlier frames, got {v.shape}")
    if v.shape[0] < ctx.min_vertex_count:
        raise ValueError(f"frame {fit.frame}: {v.shape[0]} vertices but faces index up to {ctx.min_vertex_count - 1}")
    if not np.isfinite(v).all():
        return None
    return v


def to_head_frame(vertices: np.ndarray, head_R: np.ndarray, head_t: np.ndarray, exact: bool = True) -> np.ndarray:
    """Camera-frame points (V, 3) to the head (template) frame: ``head_R.T @ (x - head_t)``.

    Row-vector form: ``(x - t) @ R``. Returns float32 (V, 3), computed in float64 (``exact``) or in float32
    (4x faster; about 1e-5 mm off at 600 mm: for figures such as the report's jitter, not for exports).
    """
    dtype = np.float64 if exact else np.float32
    R = np.asarray(head_R, dtype).reshape(3, 3)
    t = np.asarray(head_t, dtype).reshape(3)
    return ((np.asarray(vertices, dtype) - t) @ R).astype(np.float32, copy=False)


def status_code(status: str) -> int:
    """Index of ``status`` in :data:`STATUSES` (ValueError for anything else)."""
    try:
        return STATUSES.index(status)
    except ValueError:
        raise ValueError(f"frame status must be one of {STATUSES}, got {status!r}") from None


class ExportAborted(Exception):
    """Thrown into a :class:`PendingFile`'s atomic context to discard the temporary file."""


class PendingFile:
    """A take-long output: a temporary sibling of ``target`` that ``commit()`` renames over it.

    Wraps :func:`capture.io.atomic.atomic_path` across calls (it is entered at construction and left
    by :meth:`commit`, which fsyncs and renames, or :meth:`discard`, which deletes the temp file).
    """

    def __init__(self, target: Path):
        self.target = Path(target)
        self._cm = atomic_path(self.target)
        self.tmp: Path = self._cm.__enter__()
        self._open = True

    def commit(self) -> Path:
        if self._open:
            self._open = False
            self._cm.__exit__(None, None, None)
        return self.target

    def discard(self) -> None:
        if self._open:
            self._open = False
            exc = ExportAborted(str(self.target))
            with contextlib.suppress(ExportAborted):
                self._cm.__exit__(ExportAborted, exc, None)
            with contextlib.suppress(FileNotFoundError):
                os.unlink(self.tmp)  # belt and braces: the context removes it already
