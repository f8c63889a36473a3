"""Reading calibration footage: a video file or a folder of images, as grayscale frames.

:func:`open_footage` checks the input up front (exists, readable, frame size) and
:meth:`Footage.frames` yields ``(label, frame_number, gray)`` for evenly spaced candidates, at most
``max_candidates`` of them. Problems are one-line :class:`~capture.io.errors.CaptureError` messages.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

from capture.io.errors import CaptureError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")


def _natural_key(path: Path):
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", path.name)]


@dataclass(frozen=True)
class Footage:
    path: Path
    kind: str  # "video" or "images"
    count: int  # frames in the video / images in the folder
    image_size: tuple[int, int]  # width, height
    files: tuple[Path, ...] = ()

    def stride(self, max_candidates: int) -> int:
        return max(1, math.ceil(self.count / max(1, max_candidates)))

    def frames(self, max_candidates: int) -> Iterator[tuple[str, int, np.ndarray]]:
        """Evenly spaced frames (every ``stride``-th), grayscale uint8."""
        step = self.stride(max_candidates)
        if self.kind == "images":
            yield from self._image_frames(step)
        else:
            yield from self._video_frames(step)

    def _image_frames(self, step: int) -> Iterator[tuple[str, int, np.ndarray]]:
        import cv2

        first = self.files[0]
        for k in range(0, len(self.files), step):
            f = self.files[k]
            gray = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
            if gray is None:
                raise CaptureError(f"cannot read image {f}; remove it or convert it to PNG/JPEG")
            size = (gray.shape[1], gray.shape[0])
            if size != self.image_size:
                raise CaptureError(
                    f"images have different sizes: {first.name} is {self.image_size[0]}x{self.image_size[1]} "
                    f"but {f.name} is {size[0]}x{size[1]}; calibrate one camera at one resolution"
                )
            yield f.name, k, gray

    def _video_frames(self, step: int) -> Iterator[tuple[str, int, np.ndarray]]:
        import cv2

        cap = cv2.VideoCapture(str(self.path))
        try:
            k = 0
            while True:
                if k % step == 0:
                    ok, frame = cap.read()
                    if not ok:
                        break
                    yield f"frame {k}", k, _gray(frame)
                elif not cap.grab():
                    break
                k += 1
        finally:
            cap.release()


def _gray(frame: np.ndarray) -> np.ndarray:
    import cv2

    if frame.ndim == 3:
        frame = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
    if frame.dtype != np.uint8:  # 16-bit footage: keep the full range
        frame = cv2.normalize(frame, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    return frame


def open_footage(path: str | Path) -> Footage:
    """Check and describe the input: a folder of images or a video file OpenCV can decode."""
    import cv2

    path = Path(path)
    if not path.exists():
        raise CaptureError(f"input {path} does not exist; pass a video file or a folder of images")
    if path.is_dir():
        files = sorted((p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file()),
                       key=_natural_key)
        if not files:
            raise CaptureError(
                f"no images in folder {path} (looked for {', '.join(IMAGE_SUFFIXES)}); "
                "pass a folder of board photos or a video file"
            )
        first = cv2.imread(str(files[0]), cv2.IMREAD_GRAYSCALE)
        if first is None:
            raise CaptureError(f"cannot read image {files[0]}; remove it or convert it to PNG/JPEG")
        return Footage(path, "images", len(files), (first.shape[1], first.shape[0]), tuple(files))

    previous = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)  # our message, not FFmpeg's
    try:
        cap = cv2.VideoCapture(str(path))
        try:
            ok, frame = cap.read() if cap.isOpened() else (False, None)
            if not ok or frame is None:
                raise CaptureError(
                    f"cannot read video {path}: OpenCV cannot decode it; convert it to MP4 (H.264) "
                    "or extract the frames to a folder of images"
                )
            count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
            if count <= 0:  # some containers do not store it: count by decoding
                count = 1
                while cap.grab():
                    count += 1
        finally:
            cap.release()
    finally:
        cv2.utils.logging.setLogLevel(previous)
    return Footage(path, "video", count, (frame.shape[1], frame.shape[0]))
