"""Landmarks of a whole video, cached on disk per segment so that reruns and resumed runs are cheap.

Cache layout (``cache_dir`` is usually the run's output directory)::

    cache_dir/detections/<key>/key.json                what the key was made from (plain JSON)
    cache_dir/detections/<key>/seg_<first frame>.npz   one tracking segment's results

``key`` is the first 16 hex digits of the sha256 of: the ONNX file's sha256, the spec's canonical
JSON, the face finder (its ONNX and spec too, when it is one), the tracking options, the query points
(query detectors) and the video's identity (:func:`capture.io.video.video_identity`: size plus the first and
last MiB, so a copied or renamed file still hits the cache and a re-encoded one does not). A segment
file is written atomically when its segment is done, so an interrupted run keeps every finished
segment and a resumed run detects only the missing ones. Segments are the independent tracking units
of :mod:`capture.detector.runtime` (``TrackOptions.segment`` frames aligned to absolute frame numbers),
so a resumed run gives exactly the results of an uninterrupted one.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from capture.io.atomic import atomic_path, write_json
from capture.io.rows import SpilledRows
from capture.detector.runtime import Detector, FrameLandmarks, TrackState, Lane
from capture.io.errors import CaptureError
from capture.io.video import FramePool, VideoReader, video_identity

CACHE_FORMAT = 1
MEMORY_BUDGET_BYTES = 1 << 30   # decoded frames held at once (limits how many segments run side by side)


@dataclass
class LandmarkTrack:
    """Landmarks of the frames of one video (arrays over T frames, full-frame px, OpenCV centres)."""

    detector: str
    frame_index: np.ndarray            # (T,) int64
    points: np.ndarray                 # (T, L, 2) float64, NaN where no face
    confidence: np.ndarray | None      # (T, L), None when the model gives none
    sigma_px: np.ndarray | None        # (T, L) frame px, when the model gives sigma_px
    presence: np.ndarray | None        # (T,), when the model gives a presence score
    face_found: np.ndarray             # (T,) bool
    crops: np.ndarray                  # (T, 4) cx, cy, size, angle_deg (NaN when no crop)
    depth: np.ndarray | None = None    # (T, L) frame px, when the model gives xyz landmarks (a hint)
    fps: float = 0.0
    image_size: tuple[int, int] = (0, 0)
    cached_frames: int = 0             # of the segment frames, how many came from the cache
    detected_frames: int = 0           # ... and how many were detected in this call

    def __len__(self) -> int:
        return len(self.frame_index)

    def save_npz(self, path: str | Path) -> Path:
        """Write the track as an NPZ (plain arrays, loadable without pickle) atomically."""
        arrays = {"frame_index": self.frame_index, "points": self.points, "face_found": self.face_found,
                  "crops": self.crops, "fps": np.float64(self.fps),
                  "image_size": np.asarray(self.image_size, np.int64), "detector": np.str_(self.detector)}
        for k in ("confidence", "sigma_px", "presence", "depth"):
            if getattr(self, k) is not None:
                arrays[k] = getattr(self, k)
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as fh:
                np.savez(fh, **arrays)
        return Path(path)

    @classmethod
    def load_npz(cls, path: str | Path) -> "LandmarkTrack":
        from capture.io.arrays import load_npz

        g = load_npz(path, "landmark track", "delete it (or rerun with --overwrite) to detect again",
                     required=("detector", "frame_index", "points", "face_found", "crops", "fps", "image_size"))
        return cls(detector=str(g["detector"]), frame_index=g["frame_index"], points=g["points"],
                   confidence=g.get("confidence"), sigma_px=g.get("sigma_px"), presence=g.get("presence"),
                   face_found=g["face_found"], crops=g["crops"], fps=float(g["fps"]),
                   image_size=tuple(int(v) for v in g["image_size"]), depth=g.get("depth"))


def stack_frames(detector: str, results: Sequence[FrameLandmarks], count: int) -> LandmarkTrack:
    """Stack per-frame results into a :class:`LandmarkTrack`."""
    builder = TrackBuilder(detector, count, len(results))
    for r in results:
        builder.add(r)
    return builder.track()


class TrackBuilder:
    """A :class:`LandmarkTrack` filled frame by frame (:meth:`add`), so that a stream need not hold the frames'
    :class:`FrameLandmarks` until the end: the arrays are those :func:`stack_frames` gives for the same
    results. Room for ``capacity`` frames is made up front (doubled when more come); an optional array
    (confidence, sigma_px, presence, depth) is made at the first frame that has it, NaN before.

    With ``spill_dir``, the arrays of one row per landmark (points, confidence, sigma_px, depth) are held a
    block of frames at a time and spilled to unnamed temporary files there
    (:class:`capture.io.rows.SpilledRows`), and :meth:`track` maps them read-only: the builder itself then
    holds a few numbers a frame (frame index, face found, crop, presence), whatever the take's length. The
    arrays are the same either way."""

    OPTIONAL = ("confidence", "sigma_px", "presence", "depth")
    PER_LANDMARK = ("points", "confidence", "sigma_px", "depth")

    def __init__(self, detector: str, count: int, capacity: int = 0, spill_dir: Path | None = None):
        self.detector, self.count, self.n = detector, int(count), 0
        self._cap = max(0, int(capacity))
        self._arrays: dict[str, np.ndarray] = {"frame_index": np.zeros(self._cap, np.int64),
                                               "face_found": np.zeros(self._cap, bool),
                                               "crops": np.full((self._cap, 4), np.nan)}
        self._spill_dir = None if spill_dir is None else Path(spill_dir)
        self._rows: dict[str, SpilledRows] = {}      # with spill_dir

    def __len__(self) -> int:
        return self.n

    def _row_shape(self, name: str) -> tuple[int, ...]:
        return () if name == "presence" else (self.count,)

    def _grow(self) -> None:
        cap = max(64, 2 * self._cap)
        for name, a in self._arrays.items():
            fill = name not in ("points", "frame_index", "face_found")
            b = np.full((cap,) + a.shape[1:], np.nan, a.dtype) if fill else np.zeros((cap,) + a.shape[1:], a.dtype)
            b[:self.n] = a[:self.n]
            self._arrays[name] = b
        self._cap = cap

    def _spill_row(self, name: str, value) -> None:
        rows = self._rows.get(name)
        if rows is None:
            if value is None:
                return
            dtype = np.asarray(value).dtype if name == "points" else np.float64
            rows = self._rows[name] = SpilledRows(dtype, (), self._spill_dir)
            for _ in range(self.n):     # NaN before the first frame that has it
                rows.append(None)
        rows.append(None if value is None else np.asarray(value, rows.dtype))

    def add(self, r: FrameLandmarks) -> None:
        if self.n == self._cap:
            self._grow()
        a, i = self._arrays, self.n
        spilled = self.PER_LANDMARK if self._spill_dir is not None else ()
        for name in spilled:
            self._spill_row(name, getattr(r, name))
        if "points" not in spilled:
            if "points" not in a:
                pts = np.asarray(r.points)
                a["points"] = np.zeros((self._cap,) + pts.shape, pts.dtype)
            a["points"][i] = r.points
        for name in self.OPTIONAL:
            v = getattr(r, name)
            if v is not None and name not in spilled:
                if name not in a:
                    a[name] = np.full((self._cap,) + self._row_shape(name), np.nan)
                a[name][i] = v
        a["frame_index"][i] = r.frame_index
        a["face_found"][i] = r.face_found
        a["crops"][i] = r.crop
        self.n += 1

    def frames(self) -> np.ndarray:
        """(n,) int64 frame indices added so far (a view)."""
        return self._arrays["frame_index"][:self.n]

    def track(self) -> LandmarkTrack:
        a, n = self._arrays, self.n
        got = {k: (v if len(v) == n else v[:n]) for k, v in a.items()}   # views; no copy when full
        got.update({k: rows.mapped() for k, rows in self._rows.items()})
        return LandmarkTrack(
            detector=self.detector, frame_index=got["frame_index"],
            points=got["points"] if "points" in got else np.zeros((0, self.count, 2)),
            confidence=got.get("confidence"), sigma_px=got.get("sigma_px"), presence=got.get("presence"),
            face_found=got["face_found"], crops=got["crops"], depth=got.get("depth"))


def _segment_path(d: Path, start: int) -> Path:
    return d / f"seg_{start:08d}.npz"


def _write_segment(path: Path, track: LandmarkTrack) -> None:
    arrays = {"frame_index": track.frame_index, "points": track.points, "face_found": track.face_found,
              "crops": track.crops}
    for k in ("confidence", "sigma_px", "presence", "depth"):
        v = getattr(track, k)
        if v is not None:
            arrays[k] = v
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays)


def _read_segment(path: Path, detector: str, count: int) -> list[FrameLandmarks] | None:
    try:
        from capture.io.arrays import npz_members

        npz_members(path, max_bytes=(count + 8) * 64 * 64 + (1 << 20))  # headers only: never loaded whole if crafted
        with np.load(path, allow_pickle=False) as z:
            g = {k: z[k] for k in z.files}
        if not {"frame_index", "points", "face_found", "crops"} <= set(g):
            return None
    except Exception:
        return None  # unreadable: detect again
    if g["points"].ndim != 3 or g["points"].shape[1:] != (count, 2):
        return None
    out = []
    for i in range(len(g["frame_index"])):
        out.append(FrameLandmarks(
            int(g["frame_index"][i]), g["points"][i],
            g["confidence"][i] if "confidence" in g else None,
            g["sigma_px"][i] if "sigma_px" in g else None,
            float(g["presence"][i]) if "presence" in g else None,
            bool(g["face_found"][i]), tuple(float(v) for v in g["crops"][i]),
            g["depth"][i] if "depth" in g else None))
    return out


def cache_key(detector: Detector, video_id: str, query_points: np.ndarray | None) -> dict:
    q = None if query_points is None else hashlib.sha256(
        np.ascontiguousarray(query_points, dtype=np.float32).tobytes()).hexdigest()
    return {"cache_format": CACHE_FORMAT, "detector": detector.name, **detector.identity(),
            "video": video_id, "query_sha256": q}


def _parse_frames(frames, n: int) -> list[int]:
    if frames is None:
        return list(range(n))
    if isinstance(frames, slice):
        frames = range(*frames.indices(n))
    idx = sorted(set(int(i) for i in frames))
    if idx and (idx[0] < 0 or idx[-1] >= n):
        raise CaptureError(f"requested frames {idx[0]}..{idx[-1]} but the video has frames 0..{n - 1}; "
                           f"fix --frames")
    return idx


class _Progress:
    def __init__(self, enabled: bool, total: int, label: str):
        self.bar = None
        if enabled:
            from rich.progress import (BarColumn, MofNCompleteColumn, Progress, ProgressColumn, TextColumn,
                                       TimeRemainingColumn)
            from rich.text import Text

            class Speed(ProgressColumn):
                def render(self, task):
                    return Text(f"{task.speed:.1f} frames/s" if task.speed else "- frames/s")

            self.bar = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), Speed(),
                                TimeRemainingColumn(), TextColumn("left"), transient=False)
            self.bar.start()
            self.task = self.bar.add_task(label, total=total)

    def advance(self, n: int) -> None:
        if self.bar is not None and n:
            self.bar.advance(self.task, n)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.stop()


def detect_video(video_path: str | Path, detector: Detector, cache_dir: str | Path | None = None,
                 frames: Sequence[int] | slice | None = None, progress: bool = True,
                 query_points: np.ndarray | None = None, batch: int | None = None) -> LandmarkTrack:
    """Landmarks of ``frames`` (default all) of a video, using and filling the cache in ``cache_dir``.

    ``batch``: how many tracking segments run side by side, i.e. crops per model call for a model with a
    dynamic batch (default: the detector's batch size; fewer when the decoded frames would exceed
    ``MEMORY_BUDGET_BYTES``). The
    whole segments that contain the requested frames are detected (and cached); the requested frames
    are returned in ascending order.
    """
    video_path = Path(video_path)
    q = detector._check_query(query_points)
    with VideoReader(video_path) as reader:
        info = reader.info
        wanted = _parse_frames(frames, info.frame_count)
        seg = detector.options.segment
        starts = sorted({i - i % seg for i in wanted})

        cdir = None
        if cache_dir is not None:
            key = cache_key(detector, video_identity(video_path), q)
            digest = hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:16]
            cdir = Path(cache_dir) / "detections" / digest
            if not (cdir / "key.json").is_file():
                write_json(cdir / "key.json", {**key, "video_path": str(video_path)})

        done: dict[int, list[FrameLandmarks]] = {}
        if cdir is not None:
            for s in starts:
                p = _segment_path(cdir, s)
                if p.is_file():
                    r = _read_segment(p, detector.name, detector.count)
                    if r is not None:
                        done[s] = r
        missing = [s for s in starts if s not in done]
        seg_len = {s: min(seg, info.frame_count - s) for s in starts}
        cached = sum(len(done[s]) for s in done)
        todo = sum(seg_len[s] for s in missing)

        frame_bytes = info.width * info.height * 3
        lanes_max = batch if batch is not None else detector.batch_size
        lanes_max = max(1, min(lanes_max, MEMORY_BUDGET_BYTES // max(1, frame_bytes * seg)))
        bar = _Progress(progress and todo > 0, todo, f"detect {detector.name}")
        detected = 0
        pool = FramePool()     # the group's frames are decoded into the previous group's buffers
        try:
            for g in range(0, len(missing), lanes_max):
                group = missing[g:g + lanes_max]
                idx = [i for s in group for i in range(s, s + seg_len[s])]
                buf = dict(reader.frames(idx, pool))
                lanes = []
                for s in group:
                    ids = [i for i in range(s, s + seg_len[s]) if i in buf]
                    lanes.append(Lane(ids, [buf[i] for i in ids], TrackState()))
                shown = [0]

                def step(all_lanes, shown=shown):
                    n = sum(len(ln.results) for ln in all_lanes)
                    bar.advance(n - shown[0])
                    shown[0] = n

                detector.run_lanes(lanes, q, on_step=step, batch_size=lanes_max)
                pool.give(buf.values())
                del buf
                for s, lane in zip(group, lanes):
                    done[s] = lane.results
                    detected += len(lane.results)
                    if cdir is not None:
                        _write_segment(_segment_path(cdir, s), stack_frames(detector.name, lane.results,
                                                                            detector.count))
        finally:
            bar.close()

    by_index = {r.frame_index: r for s in starts for r in done[s]}
    lost = [i for i in wanted if i not in by_index]
    if lost and frames is not None:
        raise CaptureError(f"video {video_path.name} ends before frame {lost[0]} (its header says "
                           f"{info.frame_count} frames); request frames below {lost[0]}")
    results = [by_index[i] for i in wanted if i in by_index]
    track = stack_frames(detector.name, results, detector.count)
    track.fps = info.fps
    track.image_size = (info.width, info.height)
    track.cached_frames = cached
    track.detected_frames = detected
    return track


def segments_of(frames: Sequence[int], segment: int) -> list[int]:
    """First frames of the segments that contain ``frames``."""
    return sorted({int(i) - int(i) % segment for i in frames})

