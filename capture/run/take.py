"""``capture run VIDEO --actor A``: video in, animated meshes out (detect -> fit -> export, resumable).

:func:`run_take` checks every input first (:mod:`capture.run.inputs`; nothing is written on bad input),
claims the output folder (``run.json``; a folder holding another take is refused without
``--overwrite``), then runs the stages of :mod:`capture.run.stages`, each of which skips what is
already done, and writes ``report.json``. SIGTERM and Ctrl-C keep every finished segment, window and
frame file and exit with status 130; the same command resumes.

Output folder (``runs/<video stem>`` by default)::

    run.json            the take's identity, resolved settings, input fingerprints, status
    meshes/frame_XXXXXX.obj|ply, take.usdc, params.npz, landmarks.npz, overlay.mp4   (capture.export)
    export.json         the export's key and the files it wrote
    report.json         per-frame reprojection error (px), skipped frames and why, timings, versions
    detections/         detect cache per segment, and track.npz: all detected landmarks of the run
    fit/<key>/          fit cache: solved windows (resume), frames_<first>.npz chunks and done.json
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from capture.io.errors import CaptureError, Interrupted
from capture.run.inputs import RunConfig, resolve_inputs
from capture.run.report import error_stats, frame_table, versions, write_report
from capture.run.stages import LANDMARKS, detect_stage, export_stage, fit_frames, fit_stage, iter_fits
from capture.run.store import claim_run_dir, digest, write_run_json
from capture.io.signals import sigterm_as_interrupt


@dataclass
class Detection:
    """The detected landmarks of one frame, as the exporters read them (``DetectionLike``)."""

    points: np.ndarray
    confidence: np.ndarray | None
    face_found: bool


def _interrupted(out: Path, stage: str) -> Interrupted:
    return Interrupted(f"interrupted during {stage}; finished work is kept in {out}: run the same command "
                       f"to resume")


def skip_reasons(track, detector_name: str) -> dict[int, str]:
    out = {}
    for j, i in enumerate(track.frame_index):
        if not track.face_found[j]:
            why = f"no face found by detector {detector_name}"
            if track.presence is not None and np.isfinite(track.presence[j]):
                why += f" (presence score {float(track.presence[j]):.2f})"
            out[int(i)] = why
    return out


CONFIDENT = 0.5


def _finite(v) -> float | None:
    try:
        v = float(v)
    except (TypeError, ValueError):
        return None
    return v if np.isfinite(v) else None


@dataclass
class FrameSummary:
    """What the report keeps of one frame's fit (the meshes stay on disk)."""

    frame: int
    status: str
    error: float | None        # confident-landmark reprojection RMS (px) or 3D error (mm)
    error_all: float | None = None


def confident_rms(f: Any, track, row: dict[int, int]) -> float | None:
    """RMS (px) between the fitted and the detected landmarks whose confidence is >= CONFIDENT.

    The detector's low-confidence landmarks (occluded, off the face) can be far off; they carry little
    weight in the fit but would dominate a plain RMS (kept as ``reprojection_rms_all_px``).
    """
    j = row.get(int(f.frame))
    lf = getattr(f, "landmarks_fit", None)
    if j is None or lf is None or not track.face_found[j]:
        return None
    lf = np.asarray(lf, np.float64)
    p = track.points[j]
    ok = np.isfinite(p).all(1) & np.isfinite(lf).all(1)
    if track.confidence is not None:
        ok &= np.nan_to_num(track.confidence[j]) >= CONFIDENT
    return float(np.sqrt(((lf[ok] - p[ok]) ** 2).sum(1).mean())) if ok.any() else None


def summarise_fit(fit_dir: Path, track) -> list[FrameSummary]:
    row = {int(i): j for j, i in enumerate(track.frame_index)}
    return [FrameSummary(int(f.frame), str(f.status), confident_rms(f, track, row),
                         _finite(getattr(f, "reprojection_rms_px", None))) for f in iter_fits(fit_dir)]


def check_complete(requested: list[int], fitted: list[int]) -> None:
    """Every requested frame must be fitted or reported skipped; otherwise the run is not a success."""
    have = set(fitted)
    missing = [i for i in requested if i not in have]
    if missing:
        raise CaptureError(f"{len(missing)} requested frame(s) were not processed (first: {missing[0]}); "
                           f"see report.json, then rerun the same command")


def run_take(cfg: RunConfig) -> dict:
    """Run the whole take; returns the report (also written to ``OUT/report.json``)."""
    from capture.detector import LandmarkTrack
    from capture.export import ExportContext, ExportOptions
    from calib.camera_io import camera_to_dict
    from capture.io.video import VideoReader

    t_start = time.perf_counter()
    inputs = resolve_inputs(cfg)
    out, info, det = inputs.out, inputs.video_info, inputs.detector
    cam = inputs.camera.camera
    label = f"{Path(cfg.video).name} ({info.width}x{info.height}, {info.fps:g} fps, id {inputs.video_id[:12]})"
    settings = {**cfg.to_dict(), "out": str(out), "detector": str(det.onnx_path),
                "frame_range": list(inputs.frame_range), "fit_settings": inputs.fit_settings.to_dict()}
    fingerprints = {"video": inputs.video_id, "actor_weights_sha256": inputs.actor_weights_sha256,
                    "embedding_sha256": inputs.embedding_sha256, "detector": det.identity(),
                    "camera": camera_to_dict(cam)}
    claim_run_dir(out, inputs.video_id, label, cfg.overwrite)
    write_run_json(out, inputs.video_id, label, settings, fingerprints, "running")

    log: list[dict] = []
    stage = "detect"
    with sigterm_as_interrupt():
        try:
            detect_stage(inputs, out, log=log, progress=cfg.progress)
            track = LandmarkTrack.load_npz(out / LANDMARKS)
            if not track.face_found.any():
                raise CaptureError(f"detector {det.name} found no face in any of the {len(track)} requested frames; "
                                   f"check the video, --frames and the detector (its spec's crop.first_frame)")
            stage = "fit"
            fit_dir = fit_stage(inputs, track, out, log=log, progress=cfg.progress)
            frames = fit_frames(fit_dir)
            stage = "export"
            ctx = ExportContext(faces=np.asarray(inputs.actor.template.faces), fps=info.fps,
                                image_size=(info.width, info.height), camera=cam, frame_count=len(frames),
                                options=ExportOptions(), source=f"capture run {Path(cfg.video).name}, "
                                                                f"actor {inputs.actor.name}")
            dets = {int(i): Detection(track.points[j], None if track.confidence is None else track.confidence[j],
                                      bool(track.face_found[j])) for j, i in enumerate(track.frame_index)}

            def images(frames):
                with VideoReader(cfg.video) as reader:
                    yield from reader.frames(frames)

            key = {"fit": fits_key(out, inputs, track), "formats": list(cfg.formats), "fps": info.fps,
                   "video": inputs.video_id, "options": ExportOptions().__dict__}
            export_stage(fit_dir, ctx, cfg.formats, key, out, images=images, detections=dets, log=log,
                         progress=cfg.progress)
        except KeyboardInterrupt:
            raise _interrupted(out, stage) from None

    requested = list(range(*inputs.frame_range)) if cfg.frames is not None else [int(i) for i in track.frame_index]
    reasons = skip_reasons(track, det.name)
    fits = summarise_fit(fit_dir, track)
    errors = [f.error for f in fits]
    rows, skipped = frame_table(fits, "reprojection_rms_px", errors, reasons)
    for r, f in zip(rows, fits):
        r["reprojection_rms_all_px"] = f.error_all
    report = base_report("capture run", out, settings, log, t_start)
    report.update({
        "video": {"path": str(cfg.video), "identity": inputs.video_id, "frame_count": info.frame_count,
                  "fps": info.fps, "size": [info.width, info.height], "rotation_deg": info.rotation_deg},
        "actor": {"name": inputs.actor.name, "path": str(inputs.actor.path)},
        "detector": {"name": det.name, "path": str(det.onnx_path), **det.identity()},
        "camera": {**camera_to_dict(cam), "source": inputs.camera.source},
        "frames": {"requested": len(requested), "first": requested[0], "last": requested[-1],
                   "fitted": len(rows) - len(skipped), "skipped": len(skipped)},
        "error": {"kind": "reprojection error", "unit": "px", "landmarks": f"confidence >= {CONFIDENT}",
                  **error_stats(errors),
                  "all_landmarks": error_stats([r["reprojection_rms_all_px"] for r in rows])},
        "skipped_frames": skipped, "per_frame": rows, "notes": inputs.notes})
    finish_report(report, rows, "reprojection_rms_px", out)
    check_complete(requested, frames)
    write_run_json(out, inputs.video_id, label, settings, fingerprints, "done")
    return report


def fits_key(out: Path, inputs, track) -> str:
    from capture.run.stages import fit_key

    return digest(fit_key(inputs, track))


def base_report(command: str, out: Path, settings: dict, log: list[dict], t_start: float) -> dict:
    return {"format": "capture-report", "version": 1, "command": command, "out_dir": str(out),
            "versions": versions(), "settings": settings, "stages": log,
            "seconds_total": time.perf_counter() - t_start}


def finish_report(report: dict, rows: list[dict], error_key: str, out: Path) -> None:
    """Worst frame, output list; write ``report.json``."""
    import json

    vals = [(r[error_key], r["frame"]) for r in rows if r[error_key] is not None]
    report["error"]["worst_frame"] = max(vals)[1] if vals else None
    state = json.loads((out / "export.json").read_text()) if (out / "export.json").is_file() else {"files": []}
    files = state["files"]
    mesh_files = [f for f in files if f.startswith("meshes/")]
    others = [f for f in files if not f.startswith("meshes/")]
    report["outputs"] = ([f"meshes/ ({len(mesh_files)} files)"] if mesh_files else []) + others + \
        ["report.json"]
    report["output_files"] = files
    write_report(out, report)
