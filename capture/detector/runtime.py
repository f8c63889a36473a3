"""The landmark-detector runtime: load an ONNX model with its spec, crop, run in batches, map back.

Tracking and batching
---------------------
With ``crop.track`` a frame is cropped around the previous frame's landmarks, so frames of one stream
must run one after another. The runtime therefore batches *independent streams* ("lanes"): each lane
is a run of consecutive frames that starts from the face finder and then tracks; one model call takes
the current frame of every active lane. :func:`capture.detector.video.detect_video` cuts a video into
fixed segments of ``TrackOptions.segment`` frames (aligned to absolute frame numbers) and runs up to
``batch`` segments side by side. A frame's result depends only on its segment, never on the batch
size, on which other segments run with it, or on what the cache already held, so batched, unbatched
and resumed runs agree. The price is one face-finder call (and one extra model call, see ``refine``)
per segment, and a fresh start of the track at each segment boundary (which also recovers from drift).

Without ``crop.track`` every frame is cropped by the face finder and all frames are independent.

Per lane and frame:

1. No track (first frame of a lane, or the face was lost): the finder gives a crop (or no face: the
   frame is recorded with ``face_found=False`` and NaN landmarks, and the model is not run). With
   ``crop.track`` and ``TrackOptions.refine`` the model runs on the finder's crop, then again on the
   crop made from those landmarks (so the first frame is cropped like a tracked one).
2. Tracked: the crop is the bounding box of the previous frame's confident landmarks (confidence >=
   ``min_confidence``; all landmarks when the model gives no confidence), in the axes rotated by
   ``crop.align``, enlarged by ``crop.margin``, and smoothed exponentially with the previous crop.
3. A presence score below ``outputs.presence.threshold`` marks the frame ``face_found=False`` (NaN
   landmarks) and drops the track; so do fewer than ``min_confident_fraction`` confident landmarks (the
   frame's landmarks are kept, the next frame goes back to the finder).

Outputs are decoded as the spec says (:mod:`.decode`): coordinates in any order and with any extra
dimensions of size 1, ``xyz`` depth kept in frame px (``FrameLandmarks.depth``), heatmaps decoded to
sub-pixel peaks whose value is the landmark's confidence (unless the model has a confidence output).

Confidence: ``probability`` outputs are kept as given (clipped to 0..1), ``logit`` ones go through the
sigmoid (so do ``logit`` presence scores, whose threshold is then a probability). ``sigma_px`` outputs (1-sigma,
input pixels) are kept as ``sigma_px`` in frame pixels and turned into a probability-like weight
``1 / (1 + (sigma / (SIGMA_REF_FRACTION * input width))^2)`` (0.5 at a sigma of 2 % of the crop).
"""

from __future__ import annotations

import hashlib
import threading
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from capture.detector.crop import (Crop, align_angle, crop_from_landmarks, input_to_frame, output_scale,
                                   output_to_input_px, smooth_crop)
from capture.detector.decode import coordinates, heatmap_peaks, heatmap_to_input_px, per_crop, sigmoid
from capture.detector.finder import FaceFinder, make_finder
from capture.detector.preprocess import preprocess
from capture.detector.session import (ModelChecker, check_finite, check_image_input, fmt_shape,
                                      open_session)
from capture.detector.spec import DetectorSpec, load_detector_spec
from capture.io.errors import CaptureError

SIGMA_REF_FRACTION = 0.02


@dataclass(frozen=True)
class TrackOptions:
    """Runtime settings of cropping and tracking (they change results, so they are in the cache key)."""

    segment: int = 32                    # frames per independently tracked segment (video runs)
    refine: bool = True                  # re-run a finder-cropped frame on the crop from its landmarks
    min_confidence: float = 0.5          # landmarks at least this confident define the tracked crop
    min_confident_fraction: float = 0.25  # fewer confident landmarks than this: the track is lost
    smooth_centre: float = 0.7           # weight of the new crop centre/angle (1 = no smoothing)
    smooth_size: float = 0.4             # weight of the new crop size

    def __post_init__(self):
        if self.segment < 1:
            raise CaptureError(f"track segment must be at least 1 frame, got {self.segment}")
        for k in ("smooth_centre", "smooth_size"):
            v = getattr(self, k)
            if not 0 < v <= 1:
                raise CaptureError(f"track option {k} must be in (0, 1], got {v}")


@dataclass
class FrameLandmarks:
    """Landmarks of one frame in full-frame pixels (OpenCV: pixel centres at integers)."""

    frame_index: int
    points: np.ndarray                  # (L, 2) float64; NaN when no face
    confidence: np.ndarray | None       # (L,) 0..1, or None when the model gives none
    sigma_px: np.ndarray | None         # (L,) frame px, when the model gives sigma_px
    presence: float | None              # the model's face-presence score, when it gives one
    face_found: bool
    crop: tuple[float, float, float, float]  # (cx, cy, size, angle_deg) used; NaN when none
    depth: np.ndarray | None = None     # (L,) the model's z (xyz landmarks) in frame px, a relative depth hint


@dataclass
class TrackState:
    """What carries over from one frame to the next in a stream (owned by the caller)."""

    crop: Crop | None = None            # crop used for the previous frame
    points: np.ndarray | None = None    # previous frame's landmarks (L, 2)
    mask: np.ndarray | None = None      # which of them are confident enough to crop from

    def reset(self) -> None:
        self.crop, self.points, self.mask = None, None, None


@dataclass
class Job:
    lane: "Lane"
    crop: Crop
    phase: str  # "find" (finder crop), "track"


@dataclass
class Lane:
    indices: list[int]
    frames: list[np.ndarray]
    state: TrackState
    results: list[FrameLandmarks] = field(default_factory=list)
    pos: int = 0
    refine_crop: Crop | None = None

    @property
    def done(self) -> bool:
        return self.pos >= len(self.frames)


class Detector:
    """A user's ONNX landmark detector with its validated spec. Create with :meth:`load`."""

    def __init__(self, onnx_path: Path, spec: DetectorSpec, session, finder: FaceFinder, threads: int,
                 options: TrackOptions, max_batch: int):
        self.onnx_path = onnx_path
        self.spec = spec
        self.session = session
        self.finder = finder
        self.threads = threads
        self.options = options
        self.max_batch = max_batch
        self.model_calls = 0       # session.run calls (for tests and reports)
        self.model_frames = 0      # crops run through the model
        self._local = threading.local()   # per thread: the input batch's buffers (preprocess)
        self._query_dtype = np.dtype(np.float32)   # a query model's point input: float32 or float16 (_check_model)
        self._check_model()
        self.onnx_sha256 = hashlib.sha256(onnx_path.read_bytes()).hexdigest()

    # ---------------------------------------------------------------- loading
    @classmethod
    def load(cls, onnx_path: str | Path, spec_path: str | Path | None = None, threads: int = 2,
             options: TrackOptions | None = None, max_batch: int = 4) -> "Detector":
        """Load ``onnx_path`` and its spec (``spec_path``, default: same stem ``.json`` beside it).

        ``threads``: onnxruntime intra-op threads. ``max_batch``: crops per model call when the model's
        batch dimension is dynamic (a fixed batch size > 1 is filled up by repeating the last crop).
        """
        onnx_path = Path(onnx_path)
        if onnx_path.suffix.lower() == ".json":   # the spec given where the model is expected
            model = onnx_path.with_suffix(".onnx")
            raise CaptureError(f"--detector takes the ONNX model, and {onnx_path.name} is its spec; pass "
                               + (str(model) if model.is_file() else "the .onnx file that this spec describes"))
        if not onnx_path.is_file():
            raise CaptureError(f"detector model {onnx_path} does not exist; check the --detector path")
        spec = load_detector_spec(spec_path if spec_path is not None else onnx_path.with_suffix(".json"))
        session = open_session(onnx_path, threads)
        finder = make_finder(spec.crop.first_frame, threads=threads)
        return cls(onnx_path, spec, session, finder, threads, options or TrackOptions(), max(1, int(max_batch)))

    def _check_model(self) -> None:
        s = self.spec
        chk = ModelChecker(s.label, self.onnx_path.name, self.session)
        port = check_image_input(chk, s.input)
        fed = [s.input.name]
        n_img = port.shape[0]
        if s.query is not None:
            q = chk.input("query.name", s.query.name)
            fed.append(q.name)
            chk.shape("input", q, ("N", s.count, 3), f'kind is "query" and landmarks.count is {s.count}')
            if q.dtype not in ("float32", "float16"):
                chk.fail(f"query.name '{q.name}': the model input should be float32 or float16 but it is {q.dtype}")
            self._query_dtype = np.dtype(q.dtype)
            if q.shape[0] is not None and n_img is not None and q.shape[0] != n_img:
                chk.fail(f"query input '{q.name}' has batch {q.shape[0]} but image input '{port.name}' has {n_img}")
        chk.only_inputs(fed)
        lo = s.landmarks
        lm = chk.output("outputs.landmarks.name", lo.name)
        if lo.kind == "heatmap":
            form = (s.count, "H", "W") if lo.heatmap.layout == "LHW" else ("H", "W", s.count)
            chk.payload(lm, [form], f"landmarks.count is {s.count} and outputs.landmarks is a heatmap "
                        f"({lo.heatmap.layout})")
        else:
            c = lo.n_components
            pair = (s.count, c) if lo.order == "interleaved" else (c, s.count)
            chk.payload(lm, [pair, (c * s.count,)],
                        f"landmarks.count is {s.count} and outputs.landmarks holds {lo.components} "
                        f"{lo.order} ({s.count * c} values per crop)")
        chk.float_output("outputs.landmarks", lm)
        if s.confidence is not None:
            c = chk.output("outputs.confidence.name", s.confidence.name)
            chk.payload(c, [(s.count,)], f"landmarks.count is {s.count} and outputs.confidence holds one value "
                        f"per landmark")
            chk.float_output("outputs.confidence", c)
        if s.presence is not None:
            p = chk.output("outputs.presence.name", s.presence.name)
            chk.payload(p, [()], "outputs.presence holds one score per crop")
            chk.float_output("outputs.presence", p)
        self.fixed_batch = n_img
        self.batch_size = n_img if n_img is not None else self.max_batch

    # ---------------------------------------------------------------- identity
    @property
    def name(self) -> str:
        return self.spec.name

    @property
    def count(self) -> int:
        return self.spec.count

    def identity(self) -> dict:
        """Everything that decides this detector's results (for cache keys and reports)."""
        return {"onnx_sha256": self.onnx_sha256, "spec_sha256": self.spec.digest(),
                "finder": self.finder.identity(), "options": asdict(self.options)}

    # ---------------------------------------------------------------- running
    def _check_query(self, query_points: np.ndarray | None) -> np.ndarray | None:
        if self.spec.kind != "query":
            if query_points is not None:
                raise CaptureError(f"detector {self.name} is a dense detector; it takes no template points")
            return None
        if query_points is None:
            raise CaptureError(f"detector {self.name} is a query detector: it needs the actor's template points "
                               f"(A/landmarks/{self.name}.json); make that embedding first")
        q = np.asarray(query_points, dtype=np.float32).astype(self._query_dtype, copy=False)
        if q.shape != (self.count, 3):
            raise CaptureError(f"detector {self.name} takes {self.count} template points (L, 3) but got an array "
                               f"of shape {q.shape}; the landmark embedding does not match the detector")
        return q

    def run_crops(self, frames: Sequence[np.ndarray], crops: Sequence[Crop], frame_indices: Sequence[int],
                  query_points: np.ndarray | None = None) -> list[FrameLandmarks]:
        """Run the model on given crops (no finder, no tracking), in batches; results in frame px."""
        q = self._check_query(query_points)
        out: list[FrameLandmarks] = []
        bs = self.batch_size
        for i in range(0, len(frames), bs):
            out.extend(self._run_batch(frames[i:i + bs], crops[i:i + bs], frame_indices[i:i + bs], q))
        return out

    def _run_batch(self, frames, crops, indices, q) -> list[FrameLandmarks]:
        s = self.spec
        n = len(frames)
        if not hasattr(self._local, "buffers"):
            self._local.buffers = {}
        x = preprocess(frames, crops, s.input, self._local.buffers)
        if self.fixed_batch is not None and n < self.fixed_batch:
            x = np.concatenate([x, np.repeat(x[-1:], self.fixed_batch - n, axis=0)])
        feeds = {s.input.name: x}
        if q is not None:
            feeds[s.query.name] = np.ascontiguousarray(np.broadcast_to(q, (x.shape[0],) + q.shape))
        names = [s.landmarks.name] + [o.name for o in (s.confidence, s.presence) if o is not None]
        try:
            outs = self.session.run(names, feeds)
        except Exception as exc:
            msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            raise CaptureError(f"detector model {self.onnx_path.name} failed to run: {msg[:200]}; "
                               f"check the model against its spec") from None
        self.model_calls += 1
        self.model_frames += n
        res = dict(zip(names, outs))
        label = self.onnx_path.name
        lo = s.landmarks
        raw = np.asarray(res[lo.name])
        lm, depth, hm_conf = self._decode_landmarks(raw, n, label)
        check_finite(label, lo.name, lm, indices)
        conf = None
        if s.confidence is not None:
            conf = per_crop(res[s.confidence.name], n)
            if conf.shape != (n, s.count):
                raise CaptureError(f"detector model {label}: output '{s.confidence.name}' has shape "
                                   f"{fmt_shape(res[s.confidence.name].shape)}; expected (N, {s.count})")
            check_finite(label, s.confidence.name, conf, indices)
        elif hm_conf is not None:
            conf = hm_conf
        pres = None
        if s.presence is not None:
            pres = per_crop(res[s.presence.name], n)
            if pres.shape[1] != 1:
                raise CaptureError(f"detector model {label}: output '{s.presence.name}' has shape "
                                   f"{fmt_shape(res[s.presence.name].shape)}; expected one score per crop")
            pres = pres[:, 0]
            check_finite(label, s.presence.name, pres, indices)
            if s.presence.kind == "logit":
                pres = sigmoid(pres)

        results = []
        for j in range(n):
            crop = crops[j]
            q_px = lm[j] if lo.kind == "heatmap" else output_to_input_px(lm[j], lo.frame, s.input.size)
            pts = input_to_frame(q_px, crop, s.input.size)
            dep = None if depth is None else depth[j] * output_scale(lo.frame, s.input.size) * crop.size / s.input.width
            confidence = sigma = None
            if conf is not None:
                kind = "probability" if s.confidence is None else s.confidence.kind
                if kind == "probability":
                    confidence = np.clip(conf[j], 0.0, 1.0)
                elif kind == "logit":
                    confidence = sigmoid(conf[j])
                else:
                    sig_in = np.abs(conf[j])  # input px
                    sigma = sig_in * crop.size / s.input.width
                    ref = SIGMA_REF_FRACTION * s.input.width
                    confidence = 1.0 / (1.0 + (sig_in / ref) ** 2)
            presence = None if pres is None else float(pres[j])
            found = presence is None or presence >= s.presence.threshold
            if not found:
                pts = np.full_like(pts, np.nan)
                dep = None if dep is None else np.full_like(dep, np.nan)
            results.append(FrameLandmarks(int(indices[j]), pts, confidence, sigma, presence, found,
                                          crop.as_tuple(), dep))
        return results

    def _decode_landmarks(self, raw: np.ndarray, n: int, label: str):
        """The landmark output -> (input-frame positions (n, L, 2) in the output's ``frame`` (heatmaps:
        input px), depth (n, L) or None, heatmap confidence (n, L) or None)."""
        s = self.spec
        lo = s.landmarks
        if lo.kind == "heatmap":
            dims = [d for d in raw.shape[1:] if d != 1]
            if len(dims) == 2 and s.count == 1:
                dims = [1] + dims if lo.heatmap.layout == "LHW" else dims + [1]
            want = f"(N, {s.count}, H, W)" if lo.heatmap.layout == "LHW" else f"(N, H, W, {s.count})"
            if len(dims) != 3 or (dims[0] if lo.heatmap.layout == "LHW" else dims[2]) != s.count:
                raise CaptureError(f"detector model {label}: heatmap output '{lo.name}' is {fmt_shape(raw.shape)}; "
                                   f"the spec needs {want}")
            hm = np.asarray(raw, np.float64)[:n].reshape((n,) + tuple(dims))
            if lo.heatmap.layout == "HWL":
                hm = hm.transpose(0, 3, 1, 2)
            check_finite(label, lo.name, hm, None)
            if lo.heatmap.values == "logit":
                hm = sigmoid(hm)
            uv, peak = heatmap_peaks(hm, lo.heatmap.refine)
            q = heatmap_to_input_px(uv, (hm.shape[3], hm.shape[2]), s.input.size)
            return q, None, np.clip(peak, 0.0, 1.0)
        flat = per_crop(raw, n)
        c = lo.n_components
        if flat.shape[1] != s.count * c:
            raise CaptureError(f"detector model {label}: output '{lo.name}' is {fmt_shape(raw.shape)} for {n} "
                               f"crops; the spec (landmarks.count = {s.count}, components {lo.components}) needs "
                               f"{s.count * c} values per crop")
        xy, depth = coordinates(flat, s.count, c, lo.order)
        return xy, depth, None

    # ---------------------------------------------------------------- tracking
    def _tracked_crop(self, state: TrackState) -> Crop | None:
        s, o = self.spec, self.options
        pts = state.points[state.mask]
        angle = align_angle(state.points, s.crop.align.left, s.crop.align.right) if s.crop.align else 0.0
        new = crop_from_landmarks(pts, s.crop.margin, s.input.size, angle)
        return smooth_crop(state.crop, new, o.smooth_centre, o.smooth_size)

    def _track_mask(self, r: FrameLandmarks) -> np.ndarray | None:
        """Landmarks confident enough to crop from; None when too few are (the track is lost)."""
        mask = np.ones(self.count, bool) if r.confidence is None else r.confidence >= self.options.min_confidence
        if mask.sum() < max(1.0, self.options.min_confident_fraction * self.count):
            return None
        return mask

    def _accept(self, lane: Lane, r: FrameLandmarks, crop: Crop, frame: np.ndarray) -> None:
        """Record a frame's result and update the lane's track."""
        lane.results.append(r)
        lane.pos += 1
        st = lane.state
        if not (r.face_found and self.spec.crop.track):
            st.reset()
            return
        mask = self._track_mask(r)
        if mask is None:
            st.reset()
            return
        st.points, st.mask, st.crop = r.points, mask, crop
        nxt = crop_from_landmarks(r.points[mask], self.spec.crop.margin, self.spec.input.size)
        h, w = frame.shape[:2]
        if not (4.0 <= nxt.size <= 4.0 * max(h, w)) or not (-w < nxt.cx < 2 * w and -h < nxt.cy < 2 * h):
            st.reset()

    def _no_face(self, lane: Lane, index: int) -> None:
        nan = float("nan")
        lane.results.append(FrameLandmarks(index, np.full((self.count, 2), np.nan), None, None, None, False,
                                           (nan, nan, nan, nan)))
        lane.pos += 1
        lane.state.reset()

    def _next_job(self, lane: Lane) -> Job | None:
        s = self.spec
        while not lane.done:
            if lane.refine_crop is not None:
                crop, lane.refine_crop = lane.refine_crop, None
                return Job(lane, crop, "track")
            if s.crop.track and lane.state.points is not None:
                return Job(lane, self._tracked_crop(lane.state), "track")
            crop = self.finder.crop(lane.frames[lane.pos], s.crop.margin, s.input.size)
            if crop is None:
                self._no_face(lane, lane.indices[lane.pos])
                continue
            return Job(lane, crop, "find")
        return None

    def run_lanes(self, lanes: list[Lane], query_points: np.ndarray | None = None, on_step=None,
                  batch_size: int | None = None) -> None:
        """Advance all lanes to their end, one frame per lane per step, batching across lanes.

        ``batch_size``: crops per model call for a model with a dynamic batch (default
        :attr:`batch_size`); a fixed-batch model always gets its own size. ``on_step(lanes)`` is called
        after every step (progress display).
        """
        q = self._check_query(query_points)
        bs = self.fixed_batch or max(1, int(batch_size or self.batch_size))
        active = [ln for ln in lanes if not ln.done]
        while active:
            jobs = [j for j in (self._next_job(ln) for ln in active) if j is not None]
            for k in range(0, len(jobs), bs):
                chunk = jobs[k:k + bs]
                res = self._run_batch([j.lane.frames[j.lane.pos] for j in chunk], [j.crop for j in chunk],
                                      [j.lane.indices[j.lane.pos] for j in chunk], q)
                for job, r in zip(chunk, res):
                    lane = job.lane
                    if job.phase == "find" and r.face_found and self.spec.crop.track and self.options.refine:
                        mask = self._track_mask(r)
                        if mask is not None:
                            al = self.spec.crop.align
                            angle = align_angle(r.points, al.left, al.right) if al else 0.0
                            lane.refine_crop = crop_from_landmarks(r.points[mask], self.spec.crop.margin,
                                                                   self.spec.input.size, angle)
                            continue
                    self._accept(lane, r, job.crop, lane.frames[lane.pos])
            active = [ln for ln in active if not ln.done]
            if on_step is not None:
                on_step(lanes)

    def detect(self, frames: Sequence[np.ndarray], state: TrackState | None = None,
               frame_indices: Sequence[int] | None = None,
               query_points: np.ndarray | None = None) -> list[FrameLandmarks]:
        """Landmarks of consecutive frames of one stream (BGR uint8), in order.

        ``state`` carries the track from a previous call (pass the same object again to continue);
        frames are independent, and batched, when the spec does not track.
        """
        frames = list(frames)
        for f in frames:
            if not (isinstance(f, np.ndarray) and f.dtype == np.uint8 and f.ndim == 3 and f.shape[2] == 3):
                raise CaptureError("Detector.detect takes BGR uint8 frames of shape (H, W, 3)")
        indices = list(range(len(frames))) if frame_indices is None else [int(i) for i in frame_indices]
        if len(indices) != len(frames):
            raise CaptureError(f"Detector.detect got {len(frames)} frames but {len(indices)} frame indices")
        state = state if state is not None else TrackState()
        if self.spec.crop.track:
            lanes = [Lane(indices, frames, state)]
        else:
            lanes = [Lane([i], [f], TrackState()) for i, f in zip(indices, frames)]
        self.run_lanes(lanes, query_points)
        return [r for ln in lanes for r in ln.results]
