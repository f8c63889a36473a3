"""Face finders: where the face is in a frame without a previous frame to track from.

``crop.first_frame`` chooses one:

* ``haar``: OpenCV's bundled frontal-face Haar cascade (``haarcascade_frontalface_default.xml``) on the
  histogram-equalised grey frame; the largest detection wins.
* ``full_frame``: the whole frame, letterboxed into the detector input (no search).
* a face-detector ONNX with its own spec (:class:`~capture.detector.spec.FaceFinderSpec`): the frame is
  letterboxed into its input; boxes are read directly or decoded from SSD / BlazeFace / SCRFD anchors
  (:mod:`.decode`; SCRFD's outputs come one per anchor layer and are concatenated), scores may be logits,
  optional non-maximum suppression; the box with the highest score at or above ``scores.threshold`` wins.

Each finder returns a face box in frame pixels (outer edges ``x0, y0, x1, y1``, pixel centres at
integers) or None; :meth:`crop` turns it into the landmark detector's crop.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from capture.detector.preprocess import preprocess
from capture.detector.crop import Crop, crop_from_box, full_frame_crop, input_to_frame, output_to_input_px
from capture.detector.decode import anchor_counts, anchor_layers, decode_boxes, make_anchors, nms, sigmoid, to_xyxy
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
        sp = self.spec
        self.anchors = None
        self.part_rows: list[int] = []     # anchors per output when the outputs come one per anchor layer
        if sp.boxes.parts:
            self._check_parts(chk)
        else:
            self._check_outputs(chk)
        import hashlib

        self._identity = "onnx:" + hashlib.sha256(self.onnx_path.read_bytes()).hexdigest() + ":" + self.spec.digest()

    def identity(self) -> str:
        return self._identity

    def _check_outputs(self, chk: ModelChecker) -> None:
        """One boxes output and one scores output: (N, K, 4) boxes or (N, K, D) anchor regressors, (N, K) scores."""
        sp = self.spec
        b = chk.output("outputs.boxes.name", sp.boxes.name)
        s = chk.output("outputs.scores.name", sp.scores.name)
        if sp.anchors is not None:
            self.anchors = make_anchors(sp.input.size, sp.anchors)
            k = len(self.anchors)
            layout = ", ".join(f"stride {st}: {pc}/cell" for st, pc, _ in
                               anchor_layers(sp.anchors.strides, sp.anchors.per_cell, sp.anchors.sizes))
            why = f"anchors ({layout}) on a {sp.input.width}x{sp.input.height} input make {k} anchors"
            chk.shape("output", b, ("N", k, "D"), f"{why}, and outputs.boxes holds (N, K, 4 or more) regressors")
            if b.shape[2] is not None and b.shape[2] < 4:
                chk.fail(f"outputs.boxes '{b.name}' has {b.shape[2]} values per anchor; it needs at least 4 "
                         f"(x, y, w, h first)")
            chk.payload(s, [(k,), (k, "C")], f"{why}, and outputs.scores holds one score (or C class scores) "
                        f"per anchor", )
        else:
            chk.payload(b, [("K", 4)], "outputs.boxes holds (N, K, 4) boxes")
            chk.payload(s, [("K",), ("K", "C")], "outputs.scores holds (N, K) scores")
            nb = [d for d in b.shape[1:] if d != 1]
            ns = [d for d in s.shape[1:] if d != 1]
            if nb and ns and nb[0] is not None and ns[0] is not None and nb[0] != ns[0]:
                chk.fail(f"outputs.boxes '{b.name}' has {nb[0]} boxes but outputs.scores '{s.name}' has "
                         f"{ns[0]} scores")
        chk.float_output("outputs.boxes", b)
        chk.float_output("outputs.scores", s)

    def _check_parts(self, chk: ModelChecker) -> None:
        """Outputs given one per anchor layer (SCRFD's ``score_8, score_16, ...``): each holds its layer's
        anchors as rows, with a batch axis (N, K_l, D) or without one (K_l, D), as SCRFD is exported."""
        sp = self.spec
        self.anchors = make_anchors(sp.input.size, sp.anchors)
        self.part_rows = anchor_counts(sp.input.size, sp.anchors)
        layers = anchor_layers(sp.anchors.strides, sp.anchors.per_cell, sp.anchors.sizes)
        for l, ((stride, per, _), k) in enumerate(zip(layers, self.part_rows)):
            why = (f"anchor layer {l} (stride {stride}, {per}/cell) on a {sp.input.width}x{sp.input.height} input "
                   f"makes {k} anchors")
            for field, name, need in (("outputs.boxes.name", sp.boxes.parts[l], 4),
                                      ("outputs.scores.name", sp.scores.parts[l], 1)):
                port = chk.output(f"{field}[{l}]", name)
                rest = _part_dims(port.shape, k)
                if rest is None or (need > 1 and rest and rest[-1] is not None and rest[-1] < need):
                    what = "(N, K, 4 or more) or (K, 4 or more) regressors" if need > 1 else "(N, K) or (K, 1) scores"
                    chk.fail(f"{why}, so the model output '{name}' ({field}[{l}]) should hold {what} with K = {k} "
                             f"but it is {fmt_shape(port.raw_shape)}")
                chk.float_output(f"{field}[{l}]", port)

    def _decode(self, boxes_raw: np.ndarray, scores_raw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Raw outputs of one image -> (boxes (K, 4) xyxy in the spec's box frame, scores (K,))."""
        sp, label = self.spec, self.onnx_path.name
        b = np.asarray(boxes_raw, dtype=np.float64)[:1]
        b = b.reshape(b.shape[0], -1, b.shape[-1])[0]                      # (K, D)
        sc = np.asarray(scores_raw, dtype=np.float64)[:1]
        k = b.shape[0]
        sc = sc.reshape(k, -1) if sc.size % max(k, 1) == 0 and sc.size else sc.reshape(-1, 1)
        if sc.shape[0] != k:
            raise CaptureError(f"face detector {label}: output '{sp.boxes.name}' has {k} boxes but "
                               f"'{sp.scores.name}' has {sc.shape[0]} scores {fmt_shape(np.shape(scores_raw))}; "
                               f"fix the model")
        if sc.shape[1] > 1 and sp.scores.column is None:
            raise CaptureError(f"face detector spec {sp.label}: outputs.scores '{sp.scores.name}' has "
                               f"{sc.shape[1]} values per box; set outputs.scores.column to the face class")
        col = sp.scores.column or 0
        if col >= sc.shape[1]:
            raise CaptureError(f"face detector spec {sp.label}: outputs.scores.column is {col} but "
                               f"'{sp.scores.name}' has {sc.shape[1]} values per box")
        sc = sc[:, col]
        check_finite(label, sp.scores.name, sc[None])
        if sp.scores.kind == "logit":
            sc = sigmoid(sc)
        if self.anchors is not None:
            if k != len(self.anchors):
                raise CaptureError(f"face detector {label}: output '{sp.boxes.name}' has {k} rows but the "
                                   f"anchor layout makes {len(self.anchors)}; fix the spec's anchors")
            b = decode_boxes(b, self.anchors, sp.boxes.encoding, sp.boxes.scale, sp.boxes.variances)
        elif b.shape[1] != 4:
            raise CaptureError(f"face detector {label}: output '{sp.boxes.name}' has {b.shape[1]} values per "
                               f"box; expected 4")
        return to_xyxy(b[:, :4], sp.boxes.format), sc

    def find_all(self, frame: np.ndarray) -> list[tuple[Box, float]]:
        """Every face at or above the score threshold, after NMS (when the spec has it), best first:
        [(box in frame px, score)]."""
        inp = self.spec.input
        h, w = frame.shape[:2]
        crop = full_frame_crop(w, h, inp.size)
        x = preprocess([frame], [crop], inp)
        if self.batch is not None and self.batch > 1:
            x = np.repeat(x, self.batch, axis=0)
        sp = self.spec
        outs = self.session.run(list(sp.boxes.names + sp.scores.names), {inp.name: x})
        if self.part_rows:     # one output per anchor layer: their rows in anchor order, as one image's batch
            n = len(self.part_rows)
            boxes_raw = _stack_parts(outs[:n], sp.boxes.parts, self.part_rows, self.onnx_path.name)[None]
            scores_raw = _stack_parts(outs[n:], sp.scores.parts, self.part_rows, self.onnx_path.name)[None]
        else:
            boxes_raw, scores_raw = outs
        boxes, scores = self._decode(boxes_raw, scores_raw)
        ok = scores >= self.spec.scores.threshold
        boxes, scores = boxes[ok], scores[ok]
        if len(scores) == 0:
            return []
        check_finite(self.onnx_path.name, self.spec.boxes.name, boxes)
        if self.spec.nms is not None:
            boxes, scores = nms(boxes, scores, self.spec.nms.iou, self.spec.nms.mode)
        else:
            order = np.argsort(-scores, kind="stable")
            boxes, scores = boxes[order], scores[order]
        out = []
        for bx, sc in zip(boxes, scores):
            corners = output_to_input_px(bx.reshape(2, 2), self.spec.boxes.frame, inp.size)
            # box corners are outer edges; in input px an edge at u sits at (u - 0.5) like a centre
            p = input_to_frame(corners, crop, inp.size)
            x0, y0 = p.min(axis=0)
            x1, y1 = p.max(axis=0)
            if x1 > x0 and y1 > y0:
                out.append(((float(x0), float(y0), float(x1), float(y1)), float(sc)))
        return out

    def find(self, frame: np.ndarray) -> Box | None:
        """The face with the highest score (after NMS), or None."""
        found = self.find_all(frame)
        return found[0][0] if found else None


def _unbatched(shape, k: int) -> bool:
    """Whether an output that holds ``k`` anchor rows has no batch axis: ``(k,)`` or ``(k, D)``, as SCRFD's
    single-image export gives them; anything else has the batch first."""
    return bool(shape) and shape[0] == k and len(shape) <= 2


def _part_dims(shape, k: int) -> list | None:
    """The per-anchor dimensions (size-1 ones dropped) of an output that holds ``k`` anchor rows, or None
    when it cannot (:func:`_unbatched` says whether the first axis is the batch)."""
    dims = list(shape) if _unbatched(shape, k) else list(shape)[1:]
    dims = [d for d in dims if d != 1]
    if not dims or (dims[0] is not None and dims[0] != k):
        return None
    return dims[1:]


def _stack_parts(arrays, names, rows: list[int], label: str) -> np.ndarray:
    """One image's rows of outputs given one per anchor layer -> ``(K, D)`` float64, in anchor order."""
    out = []
    for a, name, k in zip(arrays, names, rows):
        a = np.asarray(a, dtype=np.float64)
        if a.ndim and not _unbatched(a.shape, k):
            a = a[0]                                       # the first image of a batch
        if a.size == 0 or a.size % k:
            raise CaptureError(f"face detector {label}: output '{name}' {fmt_shape(np.shape(a))} does not hold "
                               f"the {k} anchors of its layer; fix the spec's anchors")
        out.append(a.reshape(k, -1))
    if len({p.shape[1] for p in out}) != 1:
        raise CaptureError(f"face detector {label}: outputs {', '.join(names)} hold different numbers of values per "
                           f"anchor ({', '.join(str(p.shape[1]) for p in out)}); fix the model")
    return np.concatenate(out)


def make_finder(first_frame: str, threads: int = 2) -> FaceFinder:
    """The finder for a spec's ``crop.first_frame`` value (an absolute ONNX path after parsing)."""
    if first_frame == "haar":
        return HaarFinder()
    if first_frame == "full_frame":
        return FullFrameFinder()
    return OnnxFaceFinder(first_frame, threads=threads)
