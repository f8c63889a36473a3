"""``capture detect``: a detector alone on a video, before any fitting.

Writes into ``OUT/detect/<detector name>/``:

* ``landmarks.npz``: the :class:`~.pipeline.LandmarkTrack` (frame px, OpenCV pixel centres; plain arrays);
* ``summary.json``: :func:`capture.detector.summary.summarise` plus what was run (detector, spec,
  video, frames, cache use);
* ``overlay.mp4`` (unless ``overlay=False``): every frame with its crop and landmarks.

Detections go through the same cache as ``capture run`` (``OUT/detections/<key>/``, :mod:`.pipeline`),
so with the same ``--out`` (default ``./runs/<video stem>`` for both) a later run reuses them.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path


from capture.io.errors import CaptureError

DETECT_DIR = "detect"


@dataclass
class DetectConfig:
    video: Path
    detector: Path | None = None       # default: the one ONNX detector in VIDEO's folder/detector/
    out: Path | None = None            # default ./runs/<video stem>
    frames: str | None = None          # START:END
    threads: int = 1
    overlay: bool = True
    progress: bool = True


def run_detect(cfg: DetectConfig, say=print) -> dict:
    """Run the detector on the video; returns the summary (also written to ``summary.json``)."""
    from capture.detector.pipeline import detect_video
    from capture.detector.runtime import Detector
    from capture.detector.summary import summarise
    from capture.io.atomic import write_json
    from capture.io.threads import limit_native_pools
    from capture.io.video import open_video
    from capture.run.inputs import default_detector, parse_frame_range

    video = Path(cfg.video)
    if not video.is_file():
        raise CaptureError(f"video {video} does not exist; check the path")
    if cfg.threads < 1:
        raise CaptureError(f"--threads must be at least 1, got {cfg.threads}")
    det_path = Path(cfg.detector) if cfg.detector is not None else default_detector(video)
    detector = Detector.load(det_path, threads=cfg.threads)
    pools = limit_native_pools(cfg.threads)
    if detector.spec.kind == "query":
        raise CaptureError(f"detector {detector.name} is a query detector: it needs an actor's template points, "
                           f"so it cannot run alone; use capture run --actor A")
    with open_video(video) as reader:
        info = reader.info
    start, end = parse_frame_range(cfg.frames, info.frame_count)
    out = Path(cfg.out) if cfg.out is not None else Path("runs") / video.stem
    if out.exists() and not out.is_dir():
        raise CaptureError(f"--out {out} is a file; give a folder")
    track = detect_video(video, detector, cache_dir=out, frames=range(start, end), progress=cfg.progress)
    d = out / DETECT_DIR / detector.name
    track.save_npz(d / "landmarks.npz")
    summary = summarise(track)
    summary["run"] = {"video": str(video), "frames": [start, end], "detector_onnx": str(det_path),
                      "spec": str(detector.spec.path), **detector.identity(),
                      "cached_frames": track.cached_frames, "detected_frames": track.detected_frames,
                      "model_calls": detector.model_calls, "thread_pools": pools}
    files = ["landmarks.npz", "summary.json"]
    if cfg.overlay:
        write_overlay(video, track, detector.spec.input.size, d / "overlay.mp4", cfg.progress)
        files.append("overlay.mp4")
    summary["files"] = [str(d / f) for f in files]
    write_json(d / "summary.json", summary)
    return summary


def write_overlay(video: Path, track, input_size: tuple[int, int], path: Path, progress: bool = True) -> Path:
    """Every frame of the track with its crop and landmarks, as an H.264 MP4 (written atomically)."""
    import cv2

    from capture.detector.overlay import draw_detection
    from capture.io.atomic import atomic_path
    from capture.io.video import VideoReader
    from capture.synth.video import VideoWriter

    pos = {int(f): i for i, f in enumerate(track.frame_index)}
    fps = track.fps if track.fps > 0 else 25.0
    with VideoReader(video) as reader, atomic_path(path) as tmp:
        w, h = reader.info.width, reader.info.height
        with VideoWriter(Path(tmp), (w, h), fps, "h264", 18) as writer:
            for idx, frame in reader.frames(sorted(pos)):
                i = pos[idx]
                conf = None if track.confidence is None else track.confidence[i]
                img = draw_detection(frame, track.points[i], conf, tuple(track.crops[i]), input_size,
                                     bool(track.face_found[i]), f"{track.detector}  frame {idx}")
                writer.write(cv2.cvtColor(img, cv2.COLOR_BGR2RGB))
    return path


def print_summary(summary: dict, console=None) -> None:
    """The summary as a few lines for the terminal."""
    from rich.console import Console

    c = console or Console(soft_wrap=True)
    s = summary
    c.print(f"[bold]{s['detector']}[/]: face in {s['frames_with_face']} of {s['frames']} frames "
            f"({100 * s['face_fraction']:.1f} %), longest gap {s['longest_gap_frames']} frames "
            f"({s['run']['cached_frames']} frames from the cache, {s['run']['detected_frames']} detected)",
            highlight=False)
    if "confidence" in s and s["confidence"]:
        q = s["confidence"]
        c.print(f"confidence: p5 {q['p5']:.3f}  median {q['p50']:.3f}  p95 {q['p95']:.3f}  "
                f"below 0.5: {100 * q['below_0.5']:.1f} %", highlight=False)
    if "presence" in s and s["presence"]:
        q = s["presence"]
        c.print(f"presence: p5 {q['p5']:.3f}  median {q['p50']:.3f}", highlight=False)
    for key, name in (("jitter_step_rms_px", "frame-to-frame motion RMS"), ("jitter_noise_rms_px", "jitter (noise) RMS")):
        q = s[key]
        if q["median"] is not None:
            c.print(f"{name} per landmark: median {q['median']:.3f} px, p95 {q['p95']:.3f} px, max "
                    f"{q['max']:.3f} px", highlight=False)
    worst = s["jitter_noise_rms_px"].get("worst_landmarks")
    if worst:
        c.print("noisiest landmarks: " + ", ".join(f"{w['landmark']} ({w['px']:.2f} px)" for w in worst),
                highlight=False)
    c.print("wrote " + ", ".join(s["files"]), highlight=False)
