"""``capture run`` as a stream: decode -> detect -> fit -> export at the same time, through bounded queues.

Stages and where they run (threads of one process, but the fit; the heavy work of the threads releases
the GIL: FFmpeg decoding, onnxruntime, file writes)::

    decode thread   VideoReader: the frames of the detection segments not in the cache     -> (segment group, frames)
    detect thread   cached segments read, the others detected (Detector.run_lanes)         -> FrameLandmarks per frame
                    (these two set the pace: the fit yields them the CPU, capture.io.priority)
    crop thread     where no export reads the video's frames: the face of each frame detection is done
                    with, cut for report.html (FaceCrops), its buffer then given back to the decoder
    feed thread     the landmarks checked (capture.run.checks), their head pose by PnP
                    (capture.fit.init.PnPChain), sent to the fit process
    fit process     capture.fit.stream.fit_take_stream: each window solved as soon as      -> FrameFit per frame
                    its frames (and the initial poses they depend on) are there; it yields the CPU
                    to decoding and detection and solves from its queue of rows what they leave
                    (capture.fit.process: forked, so it has the loaded actor and a core of its own;
                    a thread where fork is not available or with ``RunConfig.side_processes`` off)
    fit thread      receives the fits, writes the fit's chunks
    main thread     the exporters (and a second VideoReader when the overlay needs images; the overlay's
                    frames are drawn by two threads of its own, capture.export.overlay) -> files;
                    the progress bar ("fit", as capture batch follows it) counts the frames written;
                    the images of the worst frames so far for report.html (report_html.WorstFrameImages):
                    the overlay's frames, or else the face crops of the crop thread
                    (report_html.FaceCrop, a JPEG of 5-25 KB a frame until exported): the video is decoded once

Queues hold at most :data:`QUEUE_FRAMES` frames, the fit process at most :data:`FIT_BACKLOG_FRAMES` rows
not yet read (detection waits when the fit or the export falls behind: :meth:`FitWorker.feed`'s
back-pressure); the decoder works at most one group of detection
segments (:data:`DECODE_BUDGET_BYTES`) ahead of the detector, and where frames are too large for two
segments in that budget (1080p), one segment is decoded and detected a piece of
:data:`DECODE_PIECE_BYTES` at a time, the track carried from piece to piece. Frames are
decoded into buffers that the detector gives back frame by frame as every lane moves past them
(:class:`capture.io.video.FramePool`, at most :func:`pool_frames`: the largest group and a frame per lane, so
the decoder fills the next group with this group's frames; the buffers' pages are mapped in one call,
:func:`capture.io.heap.populated`; other large blocks are allocated off the heap, :mod:`capture.io.heap`).
The fit process sends each frame's mesh as its map of the actor's features where it is one
(``FrameFit.mesh_map``), and the fit thread makes the vertices (:class:`capture.fit.process.FitWorker`).
What a run keeps of every frame is small: the track's per-landmark arrays and the NPZ writers' rows are
spilled to unnamed files a block at a time (:class:`capture.io.rows.SpilledRows`; the track is mapped back
read-only at the end), each frame's
``FrameLandmarks`` is let go once exported, and what stays in memory is a few numbers a frame (frame
index, crop, the report's series; ``benchmarks/bench_pipeline.py --memory``). Every thread watches one stop
event: an error or an interrupt in any stage stops all of them (a fit window being solved finishes
first, and is kept), and the error is raised in the main thread (where SIGTERM and Ctrl-C arrive; the
fit process ignores them and stops when the parent tells it).

The results are those of the stage-by-stage run (:mod:`capture.run.stages`), to the bit: detection
segments are the same independent tracking units, written to the same cache; the fit is the same
windows with the same chained keys (its window cache is resumable); the exports get the same frames.
What differs is where the fit is kept while it runs: its key hashes the whole take's landmarks, which
are not known until the end, so the windows go to ``fit/stream-<key of everything but the
landmarks>/`` and the folder is renamed to ``fit/<key>/`` (with ``done.json``) when the take ends.
``report.json`` lists per stage its busy seconds and the wall time until it finished.
"""

from __future__ import annotations

import queue
import shutil
import threading
import time
from collections import deque
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable

import numpy as np

from capture.io.atomic import write_json
from capture.io.heap import FRAMES_OFF_HEAP, set_malloc_thresholds
from capture.io.priority import BACKGROUND_NICE
from capture.io.errors import CaptureError
from capture.run.progress import StageProgress
from capture.run.report import FrameSummary, finite_or_none
from capture.run.store import array_digest, digest, read_json, save_frame_fits

QUEUE_FRAMES = 64              # fits waiting for the export
LANDMARK_QUEUE_FRAMES = 256    # landmarks waiting for the fit (a few KB each): detection goes on while the
                               # fit process imports torch and builds the actor's networks (~1.7 s)
FIT_BACKLOG_FRAMES = 512       # rows sent to the fit process and not yet read by it (~11 KB each): when the
                               # fit or the export is slower than detection, detection waits (FitWorker.feed)
DECODE_BUDGET_BYTES = 256 << 20  # decoded frames of one group of detection segments (at 720p three segments side
                                 # by side: 265 MB; one at a time held 340 MB less but made runs 5-20 % slower)
DECODE_PIECE_BYTES = 48 << 20    # a group of one segment (frames too large for two in the budget) is decoded
                                 # and detected this much at a time, its track carried over between pieces
_END = object()


class _Stopped(Exception):
    """Raised in a stage when another stage failed or the run was interrupted."""


class Pipe:
    """A bounded queue whose ``put``/``get`` give up when the pipeline's stop event is set."""

    def __init__(self, stop: threading.Event, size: int):
        self.q: queue.Queue = queue.Queue(maxsize=size)
        self.stop = stop
        self.wait_s = 0.0    # time the consumer spent waiting for items

    def put(self, item: Any) -> None:
        while True:
            if self.stop.is_set():
                raise _Stopped
            try:
                self.q.put(item, timeout=0.1)
                return
            except queue.Full:
                continue

    def get(self) -> Any:
        t0 = time.perf_counter()
        try:
            while True:
                if self.stop.is_set():
                    raise _Stopped
                try:
                    return self.q.get(timeout=0.1)
                except queue.Empty:
                    continue
        finally:
            self.wait_s += time.perf_counter() - t0

    def __iter__(self):
        while True:
            item = self.get()
            if item is _END:
                return
            yield item


@dataclass
class StageClock:
    """Busy seconds of a stage and when it finished (seconds since the pipeline started)."""

    busy: float = 0.0
    finished: float | None = None
    extra: dict = field(default_factory=dict)


class Pipeline:
    """Threads that run stage functions; the first error stops them all and is re-raised by :meth:`join`."""

    def __init__(self):
        self.stop = threading.Event()
        self.error: BaseException | None = None
        self.threads: list[threading.Thread] = []
        self.t0 = time.perf_counter()

    def pipe(self, size: int = QUEUE_FRAMES) -> Pipe:
        return Pipe(self.stop, size)

    def start(self, name: str, fn: Callable[[], None], clock: StageClock) -> None:
        def body():
            try:
                fn()
            except _Stopped:
                pass
            except BaseException as exc:   # handed to the main thread
                if self.error is None:
                    self.error = exc
                self.stop.set()
            finally:
                clock.finished = time.perf_counter() - self.t0

        t = threading.Thread(target=body, name=f"capture-{name}", daemon=True)
        self.threads.append(t)
        t.start()

    def check(self) -> None:
        if self.error is not None:
            raise self.error

    def close(self) -> None:
        """Stop every stage and wait for it (after an error or an interrupt, or at the end)."""
        self.stop.set()
        for t in self.threads:
            t.join()


class FaceCrops:
    """The report's face crops (:class:`capture.export.report_html.FaceCrop`), cut in a thread of their own
    from the frames detection is done with, which then go back to the frame pool.

    Detection hands over a frame's buffer and landmarks (:meth:`offer`) instead of giving the buffer back; the
    crop thread (:meth:`run`) cuts the crop and gives the buffer back; the export takes a frame's crop
    (:meth:`take`), waiting while it is being cut. A crop costs 0.5-1 ms a 720p frame (a resize and a JPEG, which
    let go of the GIL): in the detect thread, which sets the pace of a run, that was 0.8-1.3 s of a 1,200-frame
    take's 10-11 s."""

    def __init__(self, pipe_line: "Pipeline", pool, size: int):
        self._pipe = pipe_line.pipe(max(1, size))
        self._stop = pipe_line.stop
        self._pool = pool
        self._crops: dict[int, Any] = {}
        self._pending: set[int] = set()
        self._cond = threading.Condition()

    def offer(self, frame: int, image: np.ndarray, points: np.ndarray) -> None:
        """Detect thread: crop this frame, then give its buffer back to the pool."""
        with self._cond:
            self._pending.add(int(frame))
        self._pipe.put((int(frame), image, points))

    def close(self) -> None:
        """Detect thread: no more frames."""
        self._pipe.put(_END)

    def run(self) -> None:
        """The crop thread."""
        from capture.export.report_html import FaceCrop

        for frame, image, points in self._pipe:
            try:
                crop = FaceCrop.of(image, points)
            finally:
                self._pool.give([image])
            with self._cond:
                if crop is not None:       # no box: the report then reads that frame from the video
                    self._crops[frame] = crop
                self._pending.discard(frame)
                self._cond.notify_all()

    def take(self, frame: int):
        """Export: the crop of ``frame`` (None when it has none), once it is cut."""
        with self._cond:
            while int(frame) in self._pending:
                if self._stop.is_set():
                    raise _Stopped
                self._cond.wait(0.1)
            return self._crops.pop(int(frame), None)


# ------------------------------------------------------------------------------------ detection plan
@dataclass
class DetectPlan:
    """Which detection segments are cached and which must be detected (as :func:`detect_video`)."""

    starts: list[int]
    seg_len: dict[int, int]
    cached: dict[int, list]          # segment start -> FrameLandmarks (read from the cache)
    groups: list[list[int]]          # missing segments, grouped to run side by side
    wanted: list[int]
    cache_dir: Path | None
    info: Any
    piece: int = 1 << 30             # frames decoded at a time in a group of one segment (DECODE_PIECE_BYTES)


def plan_detection(video: Path, detector, out_dir: Path, frames, query) -> DetectPlan:
    import hashlib
    import json

    from capture.detector.pipeline import _parse_frames, _read_segment, cache_key
    from capture.io.video import VideoReader, video_identity

    with VideoReader(video) as reader:
        info = reader.info
    wanted = _parse_frames(frames, info.frame_count)
    seg = detector.options.segment
    starts = sorted({i - i % seg for i in wanted})
    key = cache_key(detector, video_identity(video), query)
    cdir = Path(out_dir) / "detections" / hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:16]
    if not (cdir / "key.json").is_file():
        write_json(cdir / "key.json", {**key, "video_path": str(video)})
    cached = {}
    for s in starts:
        p = cdir / f"seg_{s:08d}.npz"
        if p.is_file():
            r = _read_segment(p, detector.name, detector.count)
            if r is not None:
                cached[s] = r
    missing = [s for s in starts if s not in cached]
    seg_len = {s: min(seg, info.frame_count - s) for s in starts}
    frame_bytes = max(1, info.width * info.height * 3)
    lanes = max(1, min(detector.batch_size, DECODE_BUDGET_BYTES // (frame_bytes * seg)))
    return DetectPlan(starts, seg_len, cached, ramped_groups(missing, lanes), wanted, cdir, info,
                      piece=max(1, DECODE_PIECE_BYTES // frame_bytes))


def ramped_groups(segments: list[int], lanes: int, first: int = 2) -> list[list[int]]:
    """``segments`` in order, cut into groups that run side by side: ``first`` (at most ``lanes``), then
    twice as many up to ``lanes``, ``lanes`` in the middle, and halving down to 1 at the end.

    A group's landmarks reach the fit when its last frame is detected, so the first group sets when the
    fit can start and the last one how much it has left when detection ends. The first group holds two
    segments: the first window (30 frames) also waits for the head poses of the frames after it that
    its smoothing reads (8 more). With groups of 4 segments of 32 frames the fit of a 300-frame take
    started 4.5 s into the run and ended 1.3 s after the detector; the batch size barely changes the
    detector's speed (groups of 1, 2 and 4 segments: 4.5, 3.9 and 4.3 s for that take's detection).
    """
    lanes = max(1, int(lanes))
    head, tail = [], []
    n = len(segments)
    up, down = max(1, min(int(first), lanes)), 1        # the next sizes of the ramps, grown in turn
    while True:
        grew = False
        if up < lanes and sum(head) + sum(tail) + up <= n:
            head.append(up)
            up, grew = up * 2, True
        if down < lanes and sum(head) + sum(tail) + down <= n:
            tail.insert(0, down)
            down, grew = down * 2, True
        if not grew:
            break
    middle = n - sum(head) - sum(tail)
    sizes = head + [lanes] * (middle // lanes) + ([middle % lanes] if middle % lanes else []) + tail
    out, i = [], 0
    for k in sizes:
        out.append(segments[i:i + k])
        i += k
    return out


def decode_pieces(indices: list[int], piece: int) -> list[list[int]]:
    """``indices`` cut into consecutive pieces of at most ``piece`` (>= 1) frames; ``[indices]`` when they fit
    in one (an empty list stays one empty piece, so that its group still reaches the detector)."""
    piece = max(1, int(piece))
    return [indices[k:k + piece] for k in range(0, len(indices), piece)] or [indices]


def pool_frames(plan: DetectPlan) -> int:
    """Frame buffers a streamed run decodes into (:class:`capture.io.video.FramePool`'s ``cap``): the largest
    group (or piece) the detector holds, plus one frame per lane. The detector gives a group back a frame per
    lane at each step, and the decoder, faster than the detector, fills the next group into them: with the
    lanes' frames to spare it has the next group decoded by the time the detector takes this group's last
    step, so the detector waits no longer than with a segment to spare (the cap before, 29 frames more at
    720p). Each buffer is memory touched for the first time: at 720p the 29 frames were 80 MB, and the run
    1.0 s of system time longer (BENCHMARKS.md, "Streaming pipeline", twenty-first round)."""
    largest = max((min(sum(plan.seg_len[s] for s in g), plan.piece if len(g) == 1 else 1 << 30)
                   for g in plan.groups), default=1)
    lanes = max((len(g) for g in plan.groups), default=1)
    return max(1, largest + lanes)


def _frame_weights(points: np.ndarray, confidence: np.ndarray | None) -> np.ndarray:
    """One frame's row of :func:`capture.run.stages.landmark_weights`."""
    w = np.ones(points.shape[0]) if confidence is None else np.asarray(confidence, np.float64)
    ok = np.isfinite(points).all(-1) & np.isfinite(w)
    return np.where(ok, np.clip(w, 0.0, 1.0), 0.0)


# ------------------------------------------------------------------------------------------ the run
@dataclass
class StreamResult:
    track: Any                 # LandmarkTrack of the requested frames
    fit_dir: Path
    log: list
    series: Any = None         # capture.export.report_html.SeriesCollector of the exported fits
    thumbnail_images: dict = field(default_factory=dict)   # frame -> image of the worst frames (report.html)
    frames: list = field(default_factory=list)     # capture.run.report.FrameSummary per exported fit, in order
    worst_fits: dict = field(default_factory=dict)   # frame -> FrameFit of the worst frames (report.html)
    head_depths: dict = field(default_factory=dict)  # frame -> head_t z (mm) of the fitted frames
    residuals: Any = None      # capture.fit.unexplained.ResidualTally of the exported fits


def stream_take(inputs, out: Path, export_context, formats, export_key: Callable[[Any], dict],
                detection_factory: Callable[[Any], Any], progress: bool = True,
                on_exported: Callable[[Any, list], None] | None = None,
                on_detected: Callable[[], None] | None = None) -> StreamResult:
    """Run detect, fit and export of a take together (see the module docstring).

    ``export_key(track)`` gives the export's key once the take's landmarks are known;
    ``detection_factory(frame_landmarks)`` gives what the exporters read beside a fit.
    ``on_exported(series, frames)`` is called once every fit was handed to the exporters, before they
    finish their files: the report's :class:`capture.export.report_html.SeriesCollector` (with the frames'
    detections) and :attr:`StreamResult.frames` (complete by then), so that the report's figures are drawn
    while the files are written.
    ``on_detected()`` is called by the detect thread once the take's last landmarks are handed to the fit: from
    then on a core is left for work that waits for the end (the report's figure process imports matplotlib).
    Returns the track, the finished fit folder and the stage log (detect, fit, export).
    """
    from capture.detector.pipeline import TrackBuilder, _segment_path, _write_segment, stack_frames
    from capture.detector.runtime import Lane, TrackState
    from capture.export import EXPORTERS, open_exporters
    from capture.export.overlay_draw import confident_residuals, residual_rms
    from capture.export.report_html import SeriesCollector, WorstFrameImages
    from capture.fit.process import FitStopped, FitWorker
    from capture.fit.unexplained import ResidualTally
    from capture.run.checks import head_depth
    from capture.io.video import FramePool, VideoReader
    from capture.run.stages import DONE_JSON, EXPORT_JSON, FIT_CHUNK, LANDMARKS, fit_dir_for, fit_key, windowed_fit

    cfg = inputs.config
    det = inputs.detector
    out = Path(out)
    query = inputs.landmark_points if det.spec.kind == "query" else None
    q = det._check_query(query)
    start, end = inputs.frame_range
    frames = None if cfg.frames is None else range(start, end)
    plan = plan_detection(cfg.video, det, out, frames, q)
    wanted = set(plan.wanted)
    n_frames = len(plan.wanted)

    set_malloc_thresholds(*FRAMES_OFF_HEAP)
    pipe_line = Pipeline()
    decoded = pipe_line.pipe(1)
    landmarks = pipe_line.pipe(LANDMARK_QUEUE_FRAMES)
    fits = pipe_line.pipe(QUEUE_FRAMES)
    clocks = {k: StageClock() for k in ("decode", "detect", "feed", "fit", "export")}
    # the requested frames' landmarks, in order; the per-landmark arrays spilled to unnamed files in out
    track_rows = TrackBuilder(det.name, det.count, n_frames, spill_dir=out)
    unexported: deque = deque()                 # their FrameLandmarks until exported (bounded: FIT_BACKLOG_FRAMES)
    stats = {"detected": 0, "cached": sum(len(v) for v in plan.cached.values())}

    # fit folder while the take runs: keyed by everything but the landmarks
    stream_key = {**fit_key(inputs, _EmptyTrack()), "landmarks_sha256": None,
                  "detections": {"cache": plan.cache_dir.name, "frames": [plan.wanted[0], plan.wanted[-1] + 1]
                                 if plan.wanted else []}}
    stage_dir = out / "fit" / f"stream-{digest(stream_key)[:16]}"
    stage_dir.mkdir(parents=True, exist_ok=True)

    # decoded frames' buffers, given back frame by frame as detection moves past them (release): no page
    # faults per frame, and one group and a frame per lane in all (pool_frames)
    pool = FramePool(cap=pool_frames(plan), stop=pipe_line.stop)
    want_images = any(EXPORTERS[f].needs_image for f in formats)
    # the report's thumbnails of the worst frames: where no export reads the video's frames, the face of every
    # frame detected is kept, small, until the frame is exported (and its error known); cut in a thread of its own
    crops = None if want_images else FaceCrops(pipe_line, pool, pool.cap)
    released: dict[int, int] = {}        # id(lane) -> its frames given back so far (release)

    def release(lanes) -> None:
        """``Detector.run_lanes``' ``on_step``: the frames every lane has moved past go back to the pool (through
        the crop thread, which cuts the face of each for the report first, where no export reads the frames)."""
        for lane in lanes:
            for k in range(released.get(id(lane), 0), min(lane.pos, len(lane.results))):
                image, r = lane.frames[k], lane.results[k]
                lane.frames[k] = None
                if crops is not None and r.frame_index in wanted and r.face_found:
                    crops.offer(r.frame_index, image, r.points)
                else:
                    pool.give([image])
                released[id(lane)] = k + 1

    def decode():
        with VideoReader(cfg.video) as reader:
            for group in plan.groups:
                idx = [i for s in group for i in range(s, s + plan.seg_len[s])]
                # segments side by side need all their frames; one segment goes by pieces (decode_pieces)
                pieces = decode_pieces(idx, plan.piece if len(group) == 1 else len(idx))
                for k, part in enumerate(pieces):
                    while not decoded.q.empty():    # one piece ahead of the detector, not two: memory
                        if pipe_line.stop.is_set():
                            raise _Stopped
                        time.sleep(0.005)
                    t0, waited = time.perf_counter(), pool.waited_s
                    buf = dict(reader.frames(part, pool))       # waits for buffers the detector gives back
                    clocks["decode"].busy += time.perf_counter() - t0 - (pool.waited_s - waited)
                    decoded.put((group, buf, k == len(pieces) - 1))
        decoded.put(_END)

    def detect():
        groups = iter(decoded)
        done: dict[int, list] = {}
        for s in plan.starts:
            if s in plan.cached:
                seg_results = plan.cached.pop(s)
            else:
                if s not in done:
                    group, buf, last = next(groups)
                    states = [TrackState() for _ in group]    # a lane's track, carried from piece to piece
                    results: list[list] = [[] for _ in group]
                    while True:
                        t0 = time.perf_counter()
                        lanes = []
                        for g, state in zip(group, states):
                            ids = [i for i in range(g, g + plan.seg_len[g]) if i in buf]
                            lanes.append(Lane(ids, [buf[i] for i in ids], state))
                        del buf                     # the lanes hold the frames until release() gives them back
                        released.clear()
                        det.run_lanes(lanes, q, batch_size=len(group), on_step=release)
                        release(lanes)              # every lane is done: all its frames were given back
                        for lane, res in zip(lanes, results):
                            res.extend(lane.results)
                            lane.frames = []
                        clocks["detect"].busy += time.perf_counter() - t0
                        if last:
                            break
                        _, buf, last = next(groups)
                    t0 = time.perf_counter()
                    for g, res in zip(group, results):
                        done[g] = res
                        stats["detected"] += len(res)
                        _write_segment(_segment_path(plan.cache_dir, g), stack_frames(det.name, res, det.count))
                    clocks["detect"].busy += time.perf_counter() - t0
                seg_results = done.pop(s)
            for r in seg_results:
                if r.frame_index in wanted:
                    track_rows.add(r)
                    unexported.append(r)
                    landmarks.put(r)
        if frames is not None and len(track_rows) < n_frames:   # as detect_video: the header promised more
            have = set(track_rows.frames().tolist())
            lost = next(i for i in plan.wanted if i not in have)
            raise CaptureError(f"video {Path(cfg.video).name} ends before frame {lost} (its header says "
                               f"{plan.info.frame_count} frames); request frames below {lost}")
        if crops is not None:
            crops.close()
        landmarks.put(_END)
        if on_detected is not None:
            on_detected()

    def rows():
        """The fit's rows, with the plausibility check of capture.run.checks frame by frame."""
        from capture.run.checks import landmark_problems

        found_any, problem = False, []
        for r in landmarks:
            frame_map.append(int(r.frame_index))
            found = bool(r.face_found)
            if found:
                why = landmark_problems(np.asarray(r.points)[None],
                                        None if r.confidence is None else np.asarray(r.confidence)[None])[0]
                if why:
                    found = False
                    problem[:1] = problem[:1] or [why]
            found_any |= found
            yield r.points, _frame_weights(r.points, r.confidence), found
        if not found_any and problem:
            raise CaptureError(f"detector {det.name} found a face but no frame can be fitted ({problem[0]}); "
                               f"check the detector's output decoding in its spec (docs/detector_spec.md)")
        if not found_any:
            raise CaptureError(f"detector {det.name} found no face in any of the {len(frame_map)} requested "
                               f"frames; check the video, --frames and the detector (its spec's "
                               f"crop.first_frame)")

    frame_map: list[int] = []
    how = replace(windowed_fit(inputs, stage_dir / "windows"), threads=None)

    def feed():
        try:
            worker.feed(rows(), pipe_line.stop, max_backlog=FIT_BACKLOG_FRAMES)
        except FitStopped:
            raise _Stopped from None

    def fit():
        from models.mesh_map import map_vertices

        chunks: list[str] = []
        pending: list = []
        mapped: list[bool] = []     # per pending fit: its vertices made here from its mesh map
        fitted: list[int] = []

        def flush():
            if pending:
                name = f"frames_{int(pending[0].frame):06d}.npz"
                save_frame_fits(stage_dir / name, pending, worker.basis, vertices_from_maps=all(mapped))
                chunks.append(name)
                pending.clear()
                mapped.clear()

        try:
            for ff, _ in worker.results(pipe_line.stop, make_vertices=False):
                mapped.append(ff.vertices is None and ff.mesh_map is not None)
                if mapped[-1]:
                    ff.vertices = map_vertices(ff.mesh_map, worker.basis)
                ff = replace(ff, frame=frame_map[int(ff.frame)])
                pending.append(ff)
                fitted.append(int(ff.frame))
                if len(pending) == FIT_CHUNK:
                    flush()
                fits.put(ff)
        except FitStopped:
            raise _Stopped from None
        flush()
        timings = worker.timings
        clocks["fit"].busy = float(timings.get("busy_s", 0.0))
        clocks["fit"].extra = {"chunks": chunks, "frames": fitted, "process": worker.in_process,
                               "prestarted": worker.prestarted, "thread_reason": worker.thread_reason,
                               **{k: v for k, v in timings.items() if isinstance(v, (int, float))}}
        fits.put(_END)

    worst, worst_fits = WorstFrameImages(), WorstFrameImages()
    summaries: list[FrameSummary] = []
    depths: dict[int, float] = {}
    tally = ResidualTally.on_template(inputs.actor.template_arrays, inputs.landmark_points)

    # export, in this thread. The writers are opened (pxr, av imported) before the other stages start:
    # a C extension loading in one thread while another runs torch or FFmpeg can deadlock.
    state_path = out / EXPORT_JSON
    state = read_json(state_path)
    previous = set((state or {}).get("files", [])) | set((state or {}).get("previous_files", []))
    write_json(state_path, {"key": None, "status": "running", "files": [], "previous_files": sorted(previous)})
    ctx = replace(export_context, options=replace(export_context.options, overwrite=True))
    series = SeriesCollector(inputs.actor.config.n_expressions)
    # the fit's process is forked before any thread of this run starts; a fit in a thread (no fork, e.g. a Ray
    # worker) starts importing torch at once, so the writers (pxr) are opened before it: pxr's loading in one
    # thread while another imported kornia deadlocked a batch take (the loader lock against the GIL)
    in_process = None if cfg.side_processes else False
    early = None if FitWorker.forks(in_process, cfg.threads) else open_exporters(formats, out, ctx)
    try:
        worker = FitWorker(inputs.actor, inputs.landmark_points, inputs.camera.camera, how, threads=cfg.threads,
                           in_process=in_process, nice=BACKGROUND_NICE)   # detection sets the pace (capture.io.priority)
    except BaseException:
        if early is not None:
            early.abort()
        raise
    try:
        with (early or open_exporters(formats, out, ctx)) as writers, StageProgress("fit", n_frames, progress) as bar:
            reader = VideoReader(cfg.video) if want_images else None
            pipe_line.start("decode", decode, clocks["decode"])
            pipe_line.start("detect", detect, clocks["detect"])
            if crops is not None:
                pipe_line.start("crop", crops.run, StageClock())
            pipe_line.start("feed", feed, clocks["feed"])
            pipe_line.start("fit", fit, clocks["fit"])
            source = iter(reader.frames(plan.wanted)) if reader is not None else None
            try:
                for ff in fits:
                    t0 = time.perf_counter()
                    image = None
                    for index, img in source if source is not None else ():
                        if int(index) == int(ff.frame):
                            image = img
                            break
                    detection = detection_factory(_take_landmarks(unexported, int(ff.frame)))
                    writers.write(ff, image, detection)
                    series.add(ff, detection)    # the report's series, while the fit works on (not read back)
                    face = image if crops is None else crops.take(int(ff.frame))
                    residuals = confident_residuals(ff, detection)
                    error = residual_rms(residuals)
                    if residuals is not None:
                        tally.add(int(ff.frame), *residuals)
                    # what the report reads of each frame (capture.run.take.summarise_fit, check_head_depths),
                    # so that it does not read the fit back
                    status = str(getattr(ff, "status", "fitted"))
                    summaries.append(FrameSummary(int(ff.frame), status, error,
                                                  finite_or_none(getattr(ff, "reprojection_rms_px", None))))
                    if (z := head_depth(ff)) is not None:
                        depths[int(ff.frame)] = z
                    if face is not None and worst.wants(int(ff.frame), error):
                        worst.keep(int(ff.frame), error, face)
                    if worst_fits.wants(int(ff.frame), error):   # and their fits, for the thumbnails' meshes
                        worst_fits.keep(int(ff.frame), error, ff)
                    clocks["export"].busy += time.perf_counter() - t0
                    bar.advance(1)
                pipe_line.check()
                if on_exported is not None:
                    on_exported(series, summaries)
                t_close = time.perf_counter()     # the writers finish (USD's last block, NPZ) as the block ends
            finally:
                if reader is not None:
                    reader.close()
    except _Stopped:
        pipe_line.close()
        worker.close()
        pipe_line.check()
        raise
    except BaseException:
        pipe_line.close()
        worker.close()
        raise
    clocks["export"].busy += time.perf_counter() - t_close
    pipe_line.close()
    worker.close()
    pipe_line.check()
    clocks["export"].finished = time.perf_counter() - pipe_line.t0

    # the take is done: the track, the fit under its key, the export's state
    track = track_rows.track()
    track.fps, track.image_size = plan.info.fps, (plan.info.width, plan.info.height)
    track.cached_frames, track.detected_frames = stats["cached"], stats["detected"]
    _save_track(track, out / LANDMARKS)
    key = fit_key(inputs, track)
    final = fit_dir_for(out, key)
    write_json(stage_dir / "key.json", key)
    fx = clocks["fit"].extra
    write_json(stage_dir / DONE_JSON, {"key": key, "chunks": fx.get("chunks", []), "frames": fx.get("frames", [])})
    if final.exists():
        shutil.rmtree(final)
    stage_dir.rename(final)
    rel = sorted({str(Path(f).resolve().relative_to(out.resolve())) for f in writers.paths})
    for stale in sorted(previous - set(rel)):
        p = out / stale
        if p.is_file():
            p.unlink()
    write_json(state_path, {"key": export_key(track), "status": "done", "files": rel})

    wall = time.perf_counter() - pipe_line.t0
    c = clocks
    log = [
        {"stage": "detect", "status": "skipped" if stats["detected"] == 0 else "done", "seconds": c["detect"].busy,
         "finished_after_s": c["detect"].finished, "decode_seconds": c["decode"].busy,
         "waited_for_frames_s": decoded.wait_s, "decode_waited_for_buffers_s": pool.waited_s,
         "frame_buffers": pool.made, "frames": len(track),
         "frames_detected": stats["detected"], "frames_cached": stats["cached"],
         "faces_found": int(track.face_found.sum()), "streamed": True},
        {"stage": "fit", "status": "done", "seconds": c["fit"].busy, "finished_after_s": c["fit"].finished,
         "frames": len(fx.get("frames", [])), "fit_dir": str(final), "streamed": True,
         "fit_process": bool(fx.get("process")), "fit_process_prestarted": bool(fx.get("prestarted")),
         "fit_thread_reason": fx.get("thread_reason"),
         **{k: fx[k] for k in ("query_s", "pnp_s", "solve_s", "outputs_s", "windows_solved", "windows_cached",
                                    "peak_rss_mb", "landmark_noise_px", "landmarks_per_frame",
                                    "temporal_prior_scale_min", "temporal_prior_scale_max")
            if k in fx}},
        {"stage": "export", "status": "done", "seconds": c["export"].busy, "finished_after_s": wall,
         "files": len(rel), "streamed": True},
    ]
    return StreamResult(track, final, log, series, worst.images, frames=summaries, head_depths=depths,
                        worst_fits=worst_fits.images, residuals=tally)


def _take_landmarks(unexported: deque, frame: int):
    """The FrameLandmarks of ``frame``, taken off the left of ``unexported`` (detected frames in order; the
    fits arrive in the same order, each frame once), with any older ones that were not exported."""
    while unexported and int(unexported[0].frame_index) < frame:
        unexported.popleft()
    if not unexported or int(unexported[0].frame_index) != frame:
        raise RuntimeError(f"the fit returned frame {frame}, which detection did not give it")
    return unexported.popleft()


def _save_track(track, path: Path) -> None:
    """Write ``detections/track.npz`` unless it already holds these landmarks (as the detect stage does)."""
    from capture.detector import LandmarkTrack

    new = array_digest(track.frame_index, track.points, track.confidence, track.face_found)
    if path.is_file():
        try:
            o = LandmarkTrack.load_npz(path)
            if array_digest(o.frame_index, o.points, o.confidence, o.face_found) == new:
                return
        except Exception:
            pass
    track.save_npz(path)


class _EmptyTrack:
    """Stands in for the track in :func:`fit_key` before the landmarks are known."""

    frame_index = np.zeros(0, np.int64)
    points = np.zeros((0, 0, 2))
    confidence = None
    face_found = np.zeros(0, bool)
