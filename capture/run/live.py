"""``capture live SOURCE``: the take fitted while it is captured, each frame final a fixed number of frames later.

SOURCE is a camera index (``0``), a stream URL FFmpeg reads (``rtsp://...``, ``udp://...``) or a video
file, which is played at its frame rate (as a camera would deliver it). Threads::

    capture    reads frames at the source's pace and drops (and counts) a frame rather than fall behind
               the source: one that finds the detector's queue full (``detector_busy``), or the fit
               more than two windows behind (``fit_busy``: the fit process takes rows as they come, so
               without this a fit slower than the source would queue them there and the latency grow).
               A file plays as a camera delivers it: a frame whose time has passed by a whole frame
               before it could be read is skipped (``late``), as a camera's newer frame replaces it
    detect     Detector.detect one frame at a time, carrying the track from frame to frame
    feed, fit  capture.fit.stream.fit_take_stream in a process of its own (capture.fit.process), causal:
               windows of lag + 1 frames overlapping by ``overlap``, head poses from past frames only; a
               frame is final when the window that completes it is solved, at most ``lag`` frames after
               it arrived
    main       the take's writers (params.npz, landmarks.npz, take.usdc, ...) and one JSON line per
               final frame to stdout or a UDP port

JSON line (one per frame, in frame order; lengths mm, OpenCV camera axes, ``x_cam = head_R x + head_t``)::

    {"frame": 17, "status": "fitted", "t_source_s": 0.68, "t_final_s": 0.93, "latency_s": 0.25,
     "lag_frames": 4, "head_R": [[...]], "head_t_mm": [...], "jaw_R": [[...]], "jaw_t_mm": [...],
     "expressions": {"jawOpen": 0.31, ...}, "reprojection_rms_px": 0.4}

``frame`` is the source's frame number (dropped frames leave gaps), ``t_source_s`` when it was captured
(a file: frame / fps), ``t_final_s`` when its result was final, both from the start of the capture;
``lag_frames`` how many newer frames the fit had received then. ``expressions`` are the expression
weights (the mean over the landmarks of the coefficient field; with the default 2D fit it is the same
everywhere). The take (``--out``) gets the exports of ``--formats`` and ``live.json``: frames received,
processed and dropped, lag and latency figures, settings, and two rates: ``fps_sustained``, frames
fitted per second of the source (the source's pace when nothing was dropped: what a camera of that
rate can expect), and ``fps_processed``, frames fitted per second of the whole run (its start and the
last ``lag`` frames' tail included).

:func:`run_live` with ``realtime=False`` reads every frame as fast as the pipeline takes them (never
dropping) and, with ``only_frames``, only those source frames: the offline run a live one is compared with.
"""

from __future__ import annotations

import json
import math
import queue
import socket
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable

import numpy as np

from capture.io.errors import CaptureError
from capture.run.stream import _END, Pipeline, StageClock, _frame_weights, _Stopped

DEFAULT_LAG = 5
LIVE_FORMATS = ("npz", "usd")


@dataclass
class LiveConfig:
    source: str                       # camera index, URL or file
    actor: str
    detector: Path | None = None      # default: the one ONNX in a file source's folder/detector/
    camera: Path | None = None
    out: Path | None = None           # default runs/live_<source stem or index>
    formats: tuple[str, ...] = LIVE_FORMATS
    lag: int = DEFAULT_LAG            # frames until a frame is final (window = lag + 1)
    overlap: int | None = None        # frames shared by consecutive windows (default min(2, lag - 1))
    json_to: str = "stdout"           # stdout | none | udp://HOST:PORT
    max_frames: int | None = None     # stop after this many source frames
    fps: float | None = None          # pace of a file source (default: its frame rate)
    realtime: bool = True             # False: read every frame, no pacing, no drops (offline reference)
    only_frames: tuple[int, ...] | None = None   # offline: process only these source frames
    preset: str = "default"
    seed: int = 0
    iterations: int | None = None
    threads: int = 1
    queue_frames: int = 2             # frames waiting for the detector before new ones are dropped
    progress: bool = True
    overwrite: bool = False

    def windows(self) -> tuple[int, int]:
        if self.lag < 1:
            raise CaptureError(f"--lag must be at least 1 frame, got {self.lag}")
        window = self.lag + 1
        overlap = min(2, self.lag - 1) if self.overlap is None else self.overlap
        if not 0 <= overlap < window:
            raise CaptureError(f"--overlap must be in 0..{window - 2} for --lag {self.lag}, got {overlap}")
        return window, overlap


def open_source(source: str):
    """``(cv2.VideoCapture, is_file, fps, label)`` for a camera index, a URL or a file; one-line errors."""
    import cv2

    s = str(source)
    if s.isdigit():
        cap, is_file, label = cv2.VideoCapture(int(s)), False, f"camera {s}"
    elif "://" in s:
        cap, is_file, label = cv2.VideoCapture(s, cv2.CAP_FFMPEG), False, s
    else:
        if not Path(s).is_file():
            raise CaptureError(f"live source {s} is not a camera index, a stream URL or an existing video file; "
                               f"check SOURCE")
        cap, is_file, label = cv2.VideoCapture(s), True, Path(s).name
    if not cap.isOpened():
        cap.release()
        raise CaptureError(f"cannot open live source {s}: OpenCV/FFmpeg could not read it; check the camera index, "
                           f"the URL or the file")
    cap.set(cv2.CAP_PROP_ORIENTATION_AUTO, 1)
    fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
    return cap, is_file, fps, label


class JsonSink:
    """One JSON line per frame to stdout, nowhere, or a UDP port (``udp://127.0.0.1:9000``)."""

    def __init__(self, target: str):
        self.sock = None
        self.stdout = False
        if target in ("none", ""):
            return
        if target == "stdout":
            self.stdout = True
            return
        if not target.startswith("udp://"):
            raise CaptureError(f"--json must be stdout, none or udp://HOST:PORT, got '{target}'")
        host, _, port = target[len("udp://"):].rpartition(":")
        try:
            self.addr = (host or "127.0.0.1", int(port))
        except ValueError:
            raise CaptureError(f"--json {target}: the port must be a number, e.g. udp://127.0.0.1:9000") from None
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)

    def send(self, obj: dict) -> None:
        line = json.dumps(obj, separators=(",", ":"))
        if self.stdout:
            sys.stdout.write(line + "\n")
            sys.stdout.flush()
        elif self.sock is not None:
            self.sock.sendto(line.encode(), self.addr)

    def close(self) -> None:
        if self.sock is not None:
            self.sock.close()


def _expression_names(actor, n: int) -> list[str]:
    meta = getattr(actor, "metadata", {}) or {}
    names = [s for s in meta.get("shape_names", []) if s != meta.get("neutral", "neutral")]
    return names if len(names) == n else [f"expression_{k}" for k in range(n)]


def frame_message(ff, source_frame: int, t_source: float, t_final: float, lag: int, names: list[str]) -> dict:
    """The JSON line of one final frame (see the module docstring)."""
    w = np.asarray(ff.coefficients_landmarks, np.float64).mean(0)
    r = lambda a: np.round(np.asarray(a, np.float64), 6).tolist()
    rms = float(ff.reprojection_rms_px)
    return {"frame": int(source_frame), "status": str(ff.status), "t_source_s": round(t_source, 4),
            "t_final_s": round(t_final, 4), "latency_s": round(t_final - t_source, 4), "lag_frames": int(lag),
            "head_R": r(ff.head_R), "head_t_mm": r(ff.head_t), "jaw_R": r(ff.jaw_R), "jaw_t_mm": r(ff.jaw_t),
            "expressions": {k: round(float(v), 6) for k, v in zip(names, w)},
            "reprojection_rms_px": round(rms, 4) if math.isfinite(rms) else None}


def run_live(cfg: LiveConfig, say: Callable[[str], None] | None = None) -> dict:
    """Capture, detect, fit and write ``cfg.source`` live; returns the summary (also ``OUT/live.json``)."""
    from capture.actor.package import load_actor
    from capture.detector import Detector, embedded_points, read_embedding
    from capture.detector.embedding import embedding_path
    from capture.export import ExportContext, ExportOptions
    from capture.io.threads import limit_native_pools
    from capture.run.inputs import default_detector, resolve_camera, resolve_fit_settings

    window, overlap = cfg.windows()
    settings = resolve_fit_settings(cfg.preset, cfg.seed, cfg.iterations)
    sink = JsonSink(cfg.json_to)
    cap, is_file, src_fps, label = open_source(cfg.source)
    try:
        ok, first = cap.read()
        if not ok or first is None:
            raise CaptureError(f"live source {cfg.source} gave no frame; check it")
        h, w = first.shape[:2]
        fps = float(cfg.fps or src_fps or 30.0)
        actor = load_actor(cfg.actor)
        if cfg.detector is None and not is_file:
            raise CaptureError("a camera or stream source needs --detector FILE.onnx")
        det_path = Path(cfg.detector) if cfg.detector is not None else default_detector(Path(cfg.source))
        det = Detector.load(det_path, threads=cfg.threads)
        limit_native_pools(cfg.threads)
        if det.spec.kind == "query":
            raise CaptureError(f"detector {det.name} is a query detector; capture live takes dense detectors")
        if not embedding_path(actor.path, det.name).is_file():
            raise CaptureError(f"actor '{actor.name}' has no landmark embedding for detector '{det.name}' "
                               f"({embedding_path(actor.path, det.name)} is missing)")
        emb = read_embedding(actor.path, det.name, actor.template_arrays, det.count)
        points = embedded_points(emb, actor.template_arrays)
        camera = resolve_camera(cfg.camera, w, h)
        stem = Path(str(cfg.source)).stem if is_file else str(cfg.source).replace("/", "_").replace(":", "_")
        out = Path(cfg.out) if cfg.out is not None else Path("runs") / f"live_{stem}"
        out.mkdir(parents=True, exist_ok=True)
        ctx = ExportContext(faces=actor.template_faces, fps=fps, image_size=(w, h),
                            camera=camera.camera, options=ExportOptions(overwrite=True),
                            source=f"capture live {label}, actor {actor.name}")
        return _pipeline(cfg, cap, first, is_file, fps, det, actor, points, camera, settings, window, overlap, out,
                         sink, ctx, say, label)
    finally:
        cap.release()
        sink.close()


def _pipeline(cfg, cap, first, is_file, fps, det, actor, points, camera, settings, window, overlap, out, sink, ctx,
              say, label) -> dict:
    from calib.camera_io import camera_to_dict
    from capture.detector.runtime import TrackState
    from capture.export import open_exporters
    from capture.fit.process import FitStopped, FitWorker
    from capture.fit.records import WindowedFit
    from capture.io.atomic import write_json
    from capture.io.threads import native_pools
    from capture.run.take import Detection

    pl = Pipeline()
    frames_in = queue.Queue(maxsize=max(1, cfg.queue_frames))   # capture -> detect (drops when full)
    lms = pl.pipe(max(1, cfg.queue_frames))      # small: a busy fit makes the capture drop, not queue
    fits = pl.pipe(8)
    clocks = {k: StageClock() for k in ("capture", "detect", "feed", "fit", "export")}
    stats = {"received": 0, "dropped": 0, "processed": 0, "admitted": 0, "source_s": 0.0}
    why = {"late": 0, "detector_busy": 0, "fit_busy": 0}     # the dropped frames, by reason
    results: list = []                    # the detections fed to the fit, in fit order
    position: list[int] = []              # their source frames
    fit_read = [0]                        # rows the fit had taken at its latest result (of the admitted frames)
    backlog_max = 2 * window + cfg.queue_frames
    t_src: dict[int, float] = {}          # source frame -> capture time
    only = None if cfg.only_frames is None else set(int(i) for i in cfg.only_frames)
    t_start = time.perf_counter()

    def capture():
        i, frame = 0, first
        while not pl.stop.is_set():
            if cfg.max_frames is not None and i >= cfg.max_frames:
                break
            if i > 0:
                if cfg.realtime and is_file:      # a file plays at its frame rate
                    delay = t_start + i / fps - time.perf_counter()
                    if delay > 0:
                        time.sleep(delay)
                    elif -delay >= 1.0 / fps:     # a frame late: a camera would have delivered the next one
                        if not cap.grab():
                            break
                        stats["received"] += 1
                        stats["dropped"] += 1
                        why["late"] += 1
                        stats["source_s"] = (i + 1) / fps
                        i += 1
                        continue
                ok, frame = cap.read()
                if not ok or frame is None:
                    break
            t = (i / fps) if is_file else time.perf_counter() - t_start
            stats["received"] += 1
            stats["source_s"] = (i + 1) / fps if is_file else time.perf_counter() - t_start
            if only is None or i in only:
                if cfg.realtime:
                    try:
                        if stats["admitted"] - fit_read[0] >= backlog_max:
                            stats["dropped"] += 1
                            why["fit_busy"] += 1
                        else:
                            frames_in.put_nowait((i, t, frame))
                            stats["admitted"] += 1
                    except queue.Full:
                        stats["dropped"] += 1
                        why["detector_busy"] += 1
                else:
                    while not pl.stop.is_set():
                        try:
                            frames_in.put((i, t, frame), timeout=0.1)
                            break
                        except queue.Full:
                            continue
            i += 1
        while not pl.stop.is_set():
            try:
                frames_in.put(_END, timeout=0.1)
                break
            except queue.Full:
                continue

    def detect():
        state = TrackState()
        while True:
            try:
                item = frames_in.get(timeout=0.1)
            except queue.Empty:
                if pl.stop.is_set():
                    return
                continue
            if item is _END:
                break
            i, t, frame = item
            t0 = time.perf_counter()
            r = det.detect([frame], state, [i])[0]
            clocks["detect"].busy += time.perf_counter() - t0
            t_src[i] = t
            lms.put(r)
        lms.put(_END)

    def feed():
        def rows():
            for r in lms:
                results.append(r)
                position.append(int(r.frame_index))
                yield r.points, _frame_weights(r.points, r.confidence), bool(r.face_found)

        try:
            worker.feed(rows(), pl.stop)
        except FitStopped:
            raise _Stopped from None

    def fit():
        try:
            for ff, rows_read in worker.results(pl.stop):
                j = int(ff.frame)
                fit_read[0] = rows_read
                fits.put((ff, j, rows_read - 1 - j, time.perf_counter() - t_start))
        except FitStopped:
            raise _Stopped from None
        clocks["fit"].busy = float(worker.timings.get("busy_s", 0.0))
        fits.put(_END)

    how = WindowedFit(settings, window, overlap, None, "cpu", None)
    lags, latencies = [], []
    names: list[str] = []
    # the fit's process is forked before any thread of this pipeline starts
    worker = FitWorker(actor, points, camera.camera, how, causal=True, threads=cfg.threads)
    try:
        with open_exporters(cfg.formats, out, ctx) as writers:   # (USD's import too) before the source plays
            worker.wait_ready()    # the networks are built before the source plays: no frame dropped for that
            warm_s = time.perf_counter() - t_start
            t_start = time.perf_counter()
            pl.start("capture", capture, clocks["capture"])
            pl.start("detect", detect, clocks["detect"])
            pl.start("feed", feed, clocks["feed"])
            pl.start("fit", fit, clocks["fit"])
            try:
                for ff, j, lag, t_final in fits:
                    src = position[j]
                    r = results[j]
                    ffv = replace(ff, frame=src)
                    names = names or _expression_names(actor, np.shape(ff.coefficients_landmarks)[1])
                    writers.write(ffv, None, Detection(r.points, r.confidence, bool(r.face_found)))
                    sink.send(frame_message(ffv, src, t_src[src], t_final, lag, names))
                    results[j] = None          # memory stays flat: the take's landmarks are in the writers
                    lags.append(lag)
                    latencies.append(t_final - t_src[src])
                    stats["processed"] += 1
                pl.check()
            except KeyboardInterrupt:          # Ctrl-C ends a live capture: the frames so far are the take
                pl.stop.set()
                if say:
                    say("capture live: stopped; writing the take")
    except _Stopped:                          # a stage failed: raise its error
        pl.close()
        worker.close()
        pl.check()
        raise
    except BaseException:
        pl.close()
        worker.close()
        raise
    pl.close()
    worker.close()
    wall = time.perf_counter() - t_start
    summary = {
        "format": "capture-live", "version": 1, "source": str(cfg.source), "label": label,
        "actor": str(actor.path), "detector": str(det.onnx_path), "camera": camera_to_dict(camera.camera),
        "settings": {"lag": cfg.lag, "window": window, "overlap": overlap, "fps": fps, "realtime": cfg.realtime,
                     "formats": list(cfg.formats), "fit": settings.to_dict(), "poses": "causal (past frames only)",
                     "thread_pools": native_pools()},
        "frames": {"received": stats["received"], "processed": stats["processed"], "dropped": stats["dropped"],
                   "dropped_why": why, "processed_frames": [int(p) for p in position]},
        "lag": {"max_frames": int(max(lags)) if lags else None, "mean_frames": float(np.mean(lags)) if lags else None},
        "latency_s": {"median": float(np.median(latencies)) if latencies else None,
                      "p95": float(np.percentile(latencies, 95)) if latencies else None},
        "seconds": wall, "fps_processed": stats["processed"] / wall if wall > 0 else None,
        "source_seconds": stats["source_s"], "fps_source": fps,
        "fps_sustained": stats["processed"] / stats["source_s"] if stats["source_s"] > 0 else None,
        "fit_warmup_s": warm_s,    # the fit process building the networks, before the source played
        "busy_seconds": {k: round(c.busy, 3) for k, c in clocks.items()},
        "outputs": sorted(str(Path(p).name) for p in writers.paths),
    }
    write_json(out / "live.json", summary)
    if say:
        reasons = ", ".join(f"{v} {k.replace('_', ' ')}" for k, v in why.items())
        say(f"capture live {label}: {stats['processed']} frames fitted of {stats['received']} received, "
            f"{stats['dropped']} dropped ({reasons}), {summary['fps_sustained'] or 0:.1f} frames/s of the "
            f"source's {fps:g}, lag at most {summary['lag']['max_frames']} frames, take in {out}")
    return summary
