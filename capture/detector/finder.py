"""Face finders: where the face is in a frame without a previous frame to track from.

``crop.first_frame`` chooses one:

* ``haar``: OpenCV's bundled frontal-face Haar cascade (``haarcascade_frontalface_default.xml``) on the
  histogram-equalised grey frame; the largest detection wins.
* ``full_frame``: the whole frame, letterboxed into the detector input (no search).
* a face-detector ONNX with its own spec (:class:`~capture.detector.spec.FaceFinderSpec`): the frame is
  letterboxed into its input; the box with the highest score at or above ``scores.threshold`` wins.

Each finder returns a face box in frame pixels (outer edges ``x0, y0, x1, y1``, pixel centres at
integers) or None; :meth:`crop` turns it into the landmark detector's crop.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from capture.detector.preprocess import preprocess
from capture.detector.crop import Crop, crop_from_box, full_frame_crop, input_to_frame, output_to_input_px
from capture.detector.session import ModelChecker, check_finite, check_image_input, fmt_shape, open_session
from capture.detector.spec import FaceFinderSpec, load_face_finder_spec
from capture.io.errors import CaptureError

HAAR_FILE = "haarcascade_frontalface_default.xml"

Box = tuple[float, float, float, float]


class FaceFinder:
    """Base class: ``find(frame) -> box | None``; ``crop(frame, margin, input_size) -> Crop | None``."""

    name = "base"

    def find(self, frame: np.ndarray) -> Box | None:
        raise NotImplementedError

    def crop(self, frame: np.ndarray, margin: float, input_size: tuple[int, int]) -> Crop | None:
        box = self.find(frame)
        return None if box is None else crop_from_box(*box, margin, input_size)

    def identity(self) -> str:
        """What identifies this finder's results (goes into the detection cache key)."""
        return self.name


class HaarFinder(FaceFinder):
    name = "haar"

    def __init__(self, scale_factor: float = 1.1, min_neighbors: int = 5, min_size_fraction: float = 0.1):
        import cv2

        path = Path(cv2.data.haarcascades) / HAAR_FILE
        self._cc = cv2.CascadeClassifier(str(path))
        if self._cc.empty():
            raise CaptureError(f"OpenCV's face cascade {path} is missing; reinstall "
                               f"opencv-contrib-python-headless<5 or use crop.first_frame 'full_frame'")
        self.scale_factor = scale_factor
        self.min_neighbors = min_neighbors
        self.min_size_fraction = min_size_fraction

    def identity(self) -> str:
        return f"haar:{self.scale_factor}:{self.min_neighbors}:{self.min_size_fraction}"

    def find_all(self, frame: np.ndarray) -> list[Box]:
        import cv2

        gray = frame if frame.ndim == 2 else cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
        gray = cv2.equalizeHist(gray)
        m = max(20, int(min(gray.shape[:2]) * self.min_size_fraction))
        found = self._cc.detectMultiScale(gray, scaleFactor=self.scale_factor, minNeighbors=self.min_neighbors,
                                          minSize=(m, m))
        # (x, y, w, h): first pixel column/row and extent -> outer edges
        return [(x - 0.5, y - 0.5, x + w - 0.5, y + h - 0.5) for (x, y, w, h) in np.asarray(found).reshape(-1, 4)]

    def find(self, frame: np.ndarray) -> Box | None:
        boxes = self.find_all(frame)
        if not boxes:
            return None
        return max(boxes, key=lambda b: (b[2] - b[0]) * (b[3] - b[1]))


class FullFrameFinder(FaceFinder):
    name = "full_frame"

    def find(self, frame: np.ndarray) -> Box | None:
        h, w = frame.shape[:2]
        return (-0.5, -0.5, w - 0.5, h - 0.5)

    def crop(self, frame: np.ndarray, margin: float, input_size: tuple[int, int]) -> Crop | None:
        h, w = frame.shape[:2]
        return full_frame_crop(w, h, input_size)


class OnnxFaceFinder(FaceFinder):
    """A user's face-box detector (see ``docs/detector_spec.md``, face-detector spec)."""

    name = "onnx"

    def __init__(self, onnx_path: str | Path, spec_path: str | Path | None = None, threads: int = 2):
        self.onnx_path = Path(onnx_path)
        self.spec: FaceFinderSpec = load_face_finder_spec(spec_path or self.onnx_path.with_suffix(".json"))
        self.session = open_session(self.onnx_path, threads)
        chk = ModelChecker(self.spec.label, self.onnx_path.name, self.session)
        port = check_image_input(chk, self.spec.input)
        chk.only_inputs([self.spec.input.name])
        self.batch = port.shape[0]
        b = chk.output("outputs.boxes.name", self.spec.boxes.name)
        chk.shape("output", b, ("N", "K", 4), "outputs.boxes holds (N, K, 4) boxes")
        chk.float_output("outputs.boxes", b)
        s = chk.output("outputs.scores.name", self.spec.scores.name)
        if len(s.shape) == 3:
            chk.shape("output", s, ("N", "K", 1), "outputs.scores holds (N, K) scores")
        else:
            chk.shape("output", s, ("N", "K"), "outputs.scores holds (N, K) scores")
        chk.float_output("outputs.scores", s)
        if b.shape[1] is not None and s.shape[1] is not None and b.shape[1] != s.shape[1]:
            chk.fail(f"outputs.boxes '{b.name}' has {b.shape[1]} boxes but outputs.scores '{s.name}' has "
                     f"{s.shape[1]} scores")
        import hashlib

        self._identity = "onnx:" + hashlib.sha256(self.onnx_path.read_bytes()).hexdigest() + ":" + self.spec.digest()

    def identity(self) -> str:
        return self._identity

    def find(self, frame: np.ndarray) -> Box | None:
        inp = self.spec.input
        h, w = frame.shape[:2]
        crop = full_frame_crop(w, h, inp.size)
        x = preprocess([frame], [crop], inp)
        if self.batch is not None and self.batch > 1:
            x = np.repeat(x, self.batch, axis=0)
        boxes, scores = self.session.run([self.spec.boxes.name, self.spec.scores.name], {inp.name: x})
        label = self.onnx_path.name
        boxes = np.asarray(boxes, dtype=np.float64)[0]
        scores = np.asarray(scores, dtype=np.float64)[0].reshape(-1)
        if boxes.shape[0] != scores.shape[0]:
            raise CaptureError(f"face detector {label}: output '{self.spec.boxes.name}' has {boxes.shape[0]} "
                               f"boxes but '{self.spec.scores.name}' has {scores.shape[0]} scores "
                               f"{fmt_shape(scores.shape)}; fix the model")
        check_finite(label, self.spec.scores.name, scores[None])
        ok = scores >= self.spec.scores.threshold
        if not ok.any():
            return None
        i = int(np.argmax(np.where(ok, scores, -np.inf)))
        b = boxes[i]
        check_finite(label, self.spec.boxes.name, b[None])
        fmt = self.spec.boxes.format
        if fmt == "xywh":
            b = np.array([b[0], b[1], b[0] + b[2], b[1] + b[3]])
        elif fmt == "cxcywh":
            b = np.array([b[0] - b[2] / 2, b[1] - b[3] / 2, b[0] + b[2] / 2, b[1] + b[3] / 2])
        corners = output_to_input_px(b.reshape(2, 2), self.spec.boxes.frame, inp.size)
        # box corners are outer edges; in input px an edge at u sits at (u - 0.5) like a centre
        p = input_to_frame(corners, crop, inp.size)
        x0, y0 = p.min(axis=0)
        x1, y1 = p.max(axis=0)
        if not (x1 > x0 and y1 > y0):
            return None
        return (float(x0), float(y0), float(x1), float(y1))


def make_finder(first_frame: str, threads: int = 2) -> FaceFinder:
    """The finder for a spec's ``crop.first_frame`` value (an absolute ONNX path after parsing)."""
    if first_frame == "haar":
        return HaarFinder()
    if first_frame == "full_frame":
        return FullFrameFinder()
    return OnnxFaceFinder(first_frame, threads=threads)
