"""Exporters of a ``capture run`` output directory: codecs in a registry, streaming and atomic.

Layout of ``OUT`` (the formats are chosen with ``--formats``, e.g. ``obj,usd,npz,overlay``):

==========================================  ============  ==========================================
file                                        format        what
==========================================  ============  ==========================================
``meshes/frame_<index:06d>.obj`` / ``.ply``  ``obj/ply``  one mesh per frame, template topology, mm,
                                                          camera frame (or head frame on request)
``take.usdc`` (``take.usda``)               ``usd``       time-sampled mesh, y up, mm, t = frame
``params.npz``                              ``npz``       per-frame transforms, codes, coefficients
``landmarks.npz``                           ``npz``       detected landmarks, confidence, face found
``overlay.mp4``                             ``overlay``   shaded mesh, contours, landmarks, header
``curves.csv`` (+ rig in ``take.usdc``)     ``curves``    per-frame curves; UsdSkel blend-shape rig
==========================================  ============  ==========================================

``curves`` needs the actor's rig (``ExportContext.rig``) and implies ``usd`` (:func:`parse_formats` adds it).

Usage (frames arrive one at a time; memory stays flat in the take's length)::

    ctx = ExportContext(faces=template_faces, fps=video.fps, image_size=(w, h), camera=cam,
                        frame_count=n, options=ExportOptions(mesh_frame="camera"))
    with open_exporters(parse_formats("obj,usd,npz"), out_dir, ctx) as writers:
        for fit, image, detection in frames:        # image only needed when writers.needs_image
            writers.write(fit, image, detection)
    paths = writers.paths                           # everything written

Each entry of :data:`EXPORTERS` has ``open(out_dir, context) -> writer``; a writer has
``write(frame_fit, image_bgr_or_None, detection=None)``, ``close() -> list[Path]`` (finishes and
renames into place) and ``abort()`` (removes its temporary files, leaves finished outputs alone).

Resume: per-frame mesh files that already exist are kept unless ``ExportOptions.overwrite``, so a
rerun only writes missing frames; the USD, NPZ and overlay files are rewritten whole by every run
(cheap next to the fit). Nothing is ever half-written: every file goes through
:mod:`capture.io.atomic` (see :mod:`capture.export.base`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable, Sequence

from capture.io.errors import CaptureError
from capture.export.curves import CurvesWriter
from capture.export.base import (
    MESH_FRAMES,
    STATUSES,
    DetectionLike,
    ExportContext,
    ExportOptions,
    FrameFitLike,
)
from capture.export.mesh_files import MeshSequenceWriter
from capture.export.overlay import OverlayWriter
from capture.export.params import ParamsWriter
from capture.export.usd import CAMERA_TO_USD, UsdTakeWriter

__all__ = [
    "EXPORTERS", "DEFAULT_FORMATS", "Exporter", "ExportContext", "ExportOptions", "ExportSet", "FrameFitLike",
    "DetectionLike", "STATUSES", "MESH_FRAMES", "CAMERA_TO_USD", "parse_formats", "open_exporters",
]


@dataclass(frozen=True)
class Exporter:
    """One registered format: ``open(out_dir, context)`` gives a writer for a whole take."""

    name: str
    summary: str
    needs_image: bool
    opener: Callable[[Path, ExportContext], object]

    def open(self, out_dir: str | Path, context: ExportContext):
        return self.opener(Path(out_dir), context)


EXPORTERS: dict[str, Exporter] = {
    "obj": Exporter("obj", "one OBJ mesh per frame in meshes/", False,
                    lambda d, c: MeshSequenceWriter(d, c, "obj")),
    "ply": Exporter("ply", "one binary PLY mesh per frame in meshes/", False,
                    lambda d, c: MeshSequenceWriter(d, c, "ply")),
    "usd": Exporter("usd", "take.usdc with time-sampled points", False, UsdTakeWriter),
    "npz": Exporter("npz", "params.npz and landmarks.npz", False, ParamsWriter),
    "overlay": Exporter("overlay", "overlay.mp4 quality-control video", True, OverlayWriter),
    "curves": Exporter("curves", "curves.csv (Live Link Face layout) and a UsdSkel rig in take.usdc", False,
                       CurvesWriter),
}

#: What ``capture run`` exports when ``--formats`` is not given (DESIGN.md: OBJ by default).
DEFAULT_FORMATS = ("obj", "usd", "npz", "overlay")


def parse_formats(text: str | Sequence[str]) -> tuple[str, ...]:
    """``"obj,usd,npz"`` -> ``("obj", "usd", "npz")`` (order kept, duplicates dropped, case-insensitive).

    Raises:
        CaptureError: an unknown or empty name (one line listing the known ones).
    """
    items = text.split(",") if isinstance(text, str) else list(text)
    names: list[str] = []
    for raw in items:
        name = str(raw).strip().lower()
        if name not in EXPORTERS:
            what = f"unknown export format '{name}'" if name else "empty export format"
            raise CaptureError(f"{what} in --formats; known formats: {', '.join(EXPORTERS)}")
        if name not in names:
            names.append(name)
    if not names:
        raise CaptureError(f"no export format given; known formats: {', '.join(EXPORTERS)}")
    if "curves" in names and "usd" not in names:   # the rig lives in take.usdc
        names.insert(names.index("curves"), "usd")
    return tuple(names)


class ExportSet:
    """Several open writers fed together; a context manager that aborts all on an exception."""

    def __init__(self, writers: dict[str, object]):
        self.writers = writers
        self.paths: list[Path] = []
        self._done = False

    @property
    def needs_image(self) -> bool:
        return any(getattr(w, "needs_image", False) for w in self.writers.values())

    def write(self, fit: FrameFitLike, image=None, detection: DetectionLike | None = None) -> None:
        for w in self.writers.values():
            w.write(fit, image, detection)

    def close(self) -> list[Path]:
        """Finish every writer; if one fails, the unfinished ones are aborted and the error raised."""
        paths: list[Path] = []
        pending = list(self.writers.values())
        try:
            while pending:
                paths.extend(pending[0].close())
                pending.pop(0)
        except BaseException:
            for w in pending[1:]:
                w.abort()
            self._done = True
            raise
        self._done = True
        self.paths = paths
        return paths

    def abort(self) -> None:
        if not self._done:
            self._done = True
            for w in self.writers.values():
                w.abort()

    def __enter__(self) -> "ExportSet":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


def open_exporters(formats: Iterable[str], out_dir: str | Path, context: ExportContext) -> ExportSet:
    """Open a writer per format (names from :func:`parse_formats`); on failure, abort those opened."""
    writers: dict[str, object] = {}
    try:
        for name in formats:
            writers[name] = EXPORTERS[name].open(out_dir, context)
    except BaseException:
        for w in writers.values():
            w.abort()
        raise
    return ExportSet(writers)
