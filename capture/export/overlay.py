"""Quality-control video ``overlay.mp4``: the fit drawn over every exported frame.

What is drawn (the layers of ``ExportOptions.overlay_layers``, ``capture run --overlay``; default
shaded mesh, contours, landmarks and header) is described in :mod:`capture.export.overlay_draw`: the
fitted mesh shaded semi-transparently by the project's rasteriser, its silhouette and feature contours
(lids, lips, brows) drawn crisply, the landmarks as small dots with their residuals coloured by error,
and a one-line header (frame, time code, error, flags). Sizes scale with the frame height, so the
overlay reads the same at 360p and at 4K.

Frames are drawn by :data:`DRAW_THREADS` threads (the drawing is numpy and OpenCV, which let go of
the GIL, so two threads draw about 1.6x as many frames a second as one), at most
:data:`DRAW_AHEAD` frames a thread ahead of the encoder, and encoded in order as they are drawn (nothing
else is held), into a temporary sibling that ``close()`` renames over ``overlay.mp4`` (H.264
``yuv420p`` at the video's frame rate); ``abort()`` deletes it. The encoder gets the same frames, bit for
bit, whatever the number of threads (libx264 on its own threads does not repeat its output to the bit).
Odd frame sizes are padded by one pixel on the right/bottom (yuv420p needs even sizes); pixel
coordinates are unchanged. Rewritten whole by every export run.
"""

from __future__ import annotations

from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from fractions import Fraction
from pathlib import Path

import numpy as np

from capture.io.errors import CaptureError
from capture.io.machine import usable_cores
from capture.export.base import ExportContext, FrameFitLike, PendingFile, check_vertices
from capture.export.overlay_draw import FrameRenderer, Topology, project  # noqa: F401  (project: public)

OVERLAY_FILE = "overlay.mp4"
DRAW_THREADS = 2     # threads drawing frames (no more than the process's cores; 1: drawn in the caller's thread)
DRAW_AHEAD = 2       # frames in flight per drawing thread


def _av():
    try:
        import av
    except ImportError:  # pragma: no cover - depends on the environment
        raise CaptureError("the overlay export needs PyAV: pip install av") from None
    return av


class OverlayWriter:
    """Draws each frame's fit and detections and encodes it with PyAV (libx264, yuv420p)."""

    needs_image = True

    def __init__(self, out_dir: Path, ctx: ExportContext, threads: int | None = None):
        av = _av()
        self.ctx = ctx
        self.size = ctx.image_size
        self.enc_size = (self.size[0] + self.size[0] % 2, self.size[1] + self.size[1] % 2)
        self.renderer = FrameRenderer(Topology.of(ctx.faces, getattr(ctx, "features", None)), ctx.camera,
                                      self.size, ctx.fps, tuple(ctx.options.overlay_layers))
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
        n = min(DRAW_THREADS, usable_cores()) if threads is None else int(threads)
        self._pool = ThreadPoolExecutor(n, thread_name_prefix="overlay-draw") if n > 1 else None
        self._drawing: deque[Future] = deque()     # frames being drawn, in order
        self._ahead = DRAW_AHEAD * n

    # -- drawing ------------------------------------------------------------------------------
    def _checked(self, fit: FrameFitLike, image: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """The frame's image and vertices, checked (in the caller's thread: the vertex count is state)."""
        w, h = self.size
        img = np.asarray(image)
        if img.shape != (h, w, 3) or img.dtype != np.uint8:
            raise ValueError(f"frame {fit.frame}: image expected uint8 ({h}, {w}, 3), got {img.dtype} {img.shape}")
        v = check_vertices(fit, self.ctx, self._vertex_count)
        if v is not None:
            self._vertex_count = v.shape[0]
        return img, v

    def draw(self, fit: FrameFitLike, image: np.ndarray, detection=None) -> np.ndarray:
        """The overlay of one frame (BGR uint8 of the video's size), drawn in this thread."""
        img, v = self._checked(fit, image)
        return self.renderer.render(img, fit, detection, v)

    # -- writer API ---------------------------------------------------------------------------
    def write(self, fit: FrameFitLike, image: np.ndarray | None = None, detection=None) -> None:
        if image is None:
            raise ValueError(f"frame {fit.frame}: the overlay export needs the video frame (image is None)")
        img, v = self._checked(fit, image)
        if self._pool is None:
            self._encode(self.renderer.render(img, fit, detection, v))
        else:   # drawn on a copy: the caller may reuse its image buffer once this returns
            self._drawing.append(self._pool.submit(self.renderer.draw_on, img.copy(), fit, detection, v))
            while len(self._drawing) > self._ahead:
                self._encode(self._drawing.popleft().result())
        self.frames += 1

    def _encode(self, out: np.ndarray) -> None:
        if self.enc_size != self.size:
            out = np.pad(out, ((0, self.enc_size[1] - self.size[1]), (0, self.enc_size[0] - self.size[0]), (0, 0)))
        frame = self._av.VideoFrame.from_ndarray(np.ascontiguousarray(out), format="bgr24")
        for packet in self._stream.encode(frame):
            self._container.mux(packet)

    def close(self) -> list[Path]:
        try:
            while self._drawing:
                self._encode(self._drawing.popleft().result())
            self._stop_pool()
            for packet in self._stream.encode():
                self._container.mux(packet)
            self._container.close()
            self._container = None
            return [self._file.commit()]
        except BaseException:
            self.abort()
            raise

    def abort(self) -> None:
        for f in self._drawing:
            f.cancel()
        self._drawing.clear()
        self._stop_pool()
        self._close_container()
        self._file.discard()

    def _stop_pool(self) -> None:
        pool, self._pool = getattr(self, "_pool", None), None
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)

    def _close_container(self) -> None:
        c = getattr(self, "_container", None)
        self._container = None
        if c is not None:
            try:
                c.close()
            except Exception:
                pass
