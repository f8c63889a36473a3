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

import contextlib
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from capture.io.errors import CaptureError, Interrupted
from capture.io.machine import machine
from capture.run.inputs import RunConfig, resolve_inputs
from capture.fit.unexplained import ResidualTally
from capture.run.report import (FrameSummary, error_stats, finite_or_none, frame_table, unexplained_section, versions,
                                write_report)
from capture.run.stages import LANDMARKS, detect_stage, export_stage, fit_frames, fit_stage, iter_fits
from capture.run.store import digest, open_run_dir, write_run_json
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
#: What the report's worst-frame thumbnails read of those frames' fits (not the per-point coefficients).
THUMBNAIL_FIELDS = ("vertices", "landmarks_fit", "status", "reprojection_rms_px", "error3d_mm")


def track_detection(track, row: dict[int, int], frame: int) -> Detection | None:
    """The detection of video frame ``frame`` in ``track`` (``row``: frame -> the track's row), None if not there."""
    j = row.get(int(frame))
    if j is None:
        return None
    return Detection(track.points[j], None if track.confidence is None else track.confidence[j],
                     bool(track.face_found[j]))


def summarise_fit(fit_dir: Path, track, tally=None) -> list[FrameSummary]:
    """The report's summary of every frame of a finished fit, read back from ``fit_dir`` (a streamed run
    makes the same as it exports: :attr:`capture.run.stream.StreamResult.frames`).

    A frame's error is the RMS (px) between its fitted and detected landmarks whose confidence is >= CONFIDENT:
    the detector's low-confidence landmarks (occluded, off the face) can be far off; they carry little weight in
    the fit but would dominate a plain RMS (kept as ``reprojection_rms_all_px``). The rule is
    :func:`capture.export.overlay_draw.confident_rms`'s, which the stream also ranks the report's worst frames by.
    ``tally`` (a :class:`capture.fit.unexplained.ResidualTally`) is given each frame's residuals, as the stream does.
    """
    from capture.export.overlay_draw import confident_residuals, residual_rms

    row = {int(i): j for j, i in enumerate(track.frame_index)}
    out = []
    for f in iter_fits(fit_dir, ("status", "landmarks_fit", "reprojection_rms_px")):
        residuals = confident_residuals(f, track_detection(track, row, int(f.frame)))
        if residuals is not None and tally is not None:
            tally.add(int(f.frame), *residuals)
        out.append(FrameSummary(int(f.frame), str(f.status), residual_rms(residuals),
                                finite_or_none(getattr(f, "reprojection_rms_px", None))))
    return out


def check_complete(requested: list[int], fitted: list[int]) -> None:
    """Every requested frame must be fitted or reported skipped; otherwise the run is not a success."""
    have = set(fitted)
    missing = [i for i in requested if i not in have]
    if missing:
        raise CaptureError(f"{len(missing)} requested frame(s) were not processed (first: {missing[0]}); "
                           f"see report.json, then rerun the same command")


def run_take(cfg: RunConfig) -> dict:
    """Run the whole take; returns the report (also written to ``OUT/report.json``)."""
    from capture.fit.process import prestart, release_prestarted

    t_start = time.perf_counter()
    if cfg.side_processes and not cfg.segments:   # the fit's process first: it imports torch while this one starts
        prestart()
    try:
        return _run_take(cfg, t_start)
    finally:
        release_prestarted()     # where no fit ran (all cached, or an error before it)


def _run_take(cfg: RunConfig, t_start: float) -> dict:
    from calib.camera_io import camera_to_dict
    from capture.io.threads import limit_native_pools

    pools = limit_native_pools(cfg.threads)     # before the USD writer loads pxr
    inputs = resolve_inputs(cfg)
    out, info, det = inputs.out, inputs.video_info, inputs.detector
    cam = inputs.camera.camera
    label = f"{Path(cfg.video).name} ({info.width}x{info.height}, {info.fps:g} fps, id {inputs.video_id[:12]})"
    settings = {**cfg.to_dict(), "out": str(out), "detector": str(det.onnx_path),
                "frame_range": list(inputs.frame_range), "fit_settings": inputs.fit_settings.to_dict(),
                "thread_pools": pools}
    fingerprints = {"video": inputs.video_id, "actor_weights_sha256": inputs.actor_weights_sha256,
                    "embedding_sha256": inputs.embedding_sha256, "detector": det.identity(),
                    "camera": camera_to_dict(cam)}
    with open_run_dir(out, inputs.video_id, label, cfg.overwrite) as folder, contextlib.ExitStack() as stack:
        figures = None
        if cfg.side_processes:     # imports matplotlib while the take runs (capture.export.report_figures)
            from capture.export.report_figures import FigureProcess

            # its matplotlib imported when detection ends, on the core then left idle (stream_take's on_detected)
            figures = stack.enter_context(FigureProcess(prepare_later=True))
        report = _run_in(folder, cfg, inputs, label, settings, fingerprints, t_start, figures)
    return report


def _run_in(folder, cfg: RunConfig, inputs, label: str, settings: dict, fingerprints: dict, t_start: float,
            figure_process=None) -> dict:
    """The stages and the report of :func:`run_take`, built in ``folder.work`` and committed to ``folder.out``."""
    from capture.detector import LandmarkTrack
    from capture.export import ExportContext
    from calib.camera_io import camera_to_dict
    from capture.io.video import VideoReader
    from capture.run.checks import check_detections, check_head_depths

    out, info, det = folder.work, inputs.video_info, inputs.detector
    cam = inputs.camera.camera
    write_run_json(out, inputs.video_id, label, settings, fingerprints, "running")

    log: list[dict] = []
    stage = "detect"
    options = export_options(cfg)
    ctx = ExportContext(faces=inputs.actor.template_faces, fps=info.fps,
                        image_size=(info.width, info.height), camera=cam, frame_count=0,
                        options=options, source=f"capture run {Path(cfg.video).name}, "
                                                f"actor {inputs.actor.name}",
                        **rig_and_features(inputs.actor, cfg.formats))

    def export_key(track) -> dict:
        return {"fit": fits_key(out, inputs, track), "formats": list(cfg.formats), "fps": info.fps,
                "video": inputs.video_id, "options": options.to_dict()}

    def detections_of(track) -> dict:
        return {int(i): Detection(track.points[j], None if track.confidence is None else track.confidence[j],
                                  bool(track.face_found[j])) for j, i in enumerate(track.frame_index)}

    collector = None           # the report's series, when the stream collected it
    worst_images = None        # and the images of its worst frames
    early: dict = {}           # and its figures, submitted while the stream's files were written
    summaries = depths = worst_fits = None   # and what the report reads of each frame, and the worst ones' fits
    tally = None               # and the landmark residuals' tally (capture.fit.unexplained)

    def on_exported(series, frames) -> None:
        if figure_process is not None:     # the errors of the report's rows, which are made of the same frames
            errors = {f.frame: finite_or_none(f.error) for f in frames}
            early["series"] = series.series(info.fps, inputs.actor.face_rig().names, errors, "px")
            figure_process.submit(early["series"])
    with sigterm_as_interrupt():
        try:
            streamed = None if cfg.segments else _stream_unless_fitted(inputs, out, log)
            if streamed is not None:   # detect, fit and export ran together (capture.run.stream)
                stage = "the streamed detect, fit and export"
                from capture.run.stream import stream_take

                res = stream_take(inputs, out, replace(ctx, frame_count=streamed), cfg.formats, export_key,
                                  lambda r: Detection(r.points, r.confidence, bool(r.face_found)), cfg.progress,
                                  on_exported=on_exported,
                                  on_detected=None if figure_process is None else figure_process.prepare)
                log[:] = res.log
                track, fit_dir, collector, worst_images = res.track, res.fit_dir, res.series, res.thumbnail_images
                summaries, depths, worst_fits, tally = res.frames, res.head_depths, res.worst_fits, res.residuals
                check_reasons = check_detections(track, det.name)
                frames = fit_frames(fit_dir)
                dets = detections_of(track)
            else:
                if figure_process is not None:
                    figure_process.prepare()
                if not log:
                    detect_stage(inputs, out, log=log, progress=cfg.progress)
                track = LandmarkTrack.load_npz(out / LANDMARKS)
                check_reasons = check_detections(track, det.name)
                if not track.face_found.any():
                    raise CaptureError(f"detector {det.name} found no face in any of the {len(track)} requested "
                                       f"frames; check the video, --frames and the detector (its spec's "
                                       f"crop.first_frame)")
                stage = "fit"
                try:
                    fit_dir = fit_stage(inputs, track, out, log=log, progress=cfg.progress)
                except ValueError as exc:
                    if "PnP" not in str(exc):
                        raise
                    raise CaptureError(f"no frame's landmarks give a head pose through camera "
                                       f"{inputs.camera.source} (PnP failed on every frame): check the camera file "
                                       f"and the detector's confidences") from None
                frames = fit_frames(fit_dir)
                stage = "export"
                dets = detections_of(track)

                def images(frames):
                    with VideoReader(cfg.video) as reader:
                        yield from reader.frames(frames)

                export_stage(fit_dir, replace(ctx, frame_count=len(frames)), cfg.formats, export_key(track), out,
                             images=images, detections=dets, log=log, progress=cfg.progress)
        except KeyboardInterrupt:
            raise _interrupted(out, stage) from None

    requested = list(range(*inputs.frame_range)) if cfg.frames is not None else [int(i) for i in track.frame_index]
    reasons = {**skip_reasons(track, det.name), **check_reasons}
    if summaries is None:
        tally = ResidualTally.on_template(inputs.actor.template_arrays, inputs.landmark_points)
        fits = summarise_fit(fit_dir, track, tally)
    else:
        fits = summaries
    errors = [f.error for f in fits]
    rows, skipped = frame_table(fits, "reprojection_rms_px", errors, reasons)
    for r, f in zip(rows, fits):
        r["reprojection_rms_all_px"] = f.error_all
    report = base_report("capture run", folder.out, settings, log, t_start)
    for st in log:  # a replacing run is built in folder.work and moved to folder.out
        if isinstance(st.get("fit_dir"), str):
            st["fit_dir"] = st["fit_dir"].replace(str(folder.work), str(folder.out), 1)
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
        "skipped_frames": skipped, "per_frame": rows, "notes": list(inputs.notes)})
    report["unexplained"], unexplained_notes = unexplained_section(tally, info.fps)
    report["notes"] += unexplained_notes
    implausible = check_head_depths(fit_dir, rows, depths)
    finish_report(report, rows, "reprojection_rms_px", out)
    html_report(out, report, fit_dir, inputs.actor, rows, "reprojection_rms_px", "px", info.fps, detections=dets,
                video=Path(cfg.video), camera=cam, image_size=(info.width, info.height), figure_process=figure_process,
                collector=collector, images=worst_images, submitted=early.get("series"), fits=worst_fits)
    check_complete(requested, frames)
    if implausible:
        raise CaptureError(implausible)
    write_run_json(out, inputs.video_id, label, settings, fingerprints, "done")
    folder.commit()
    return report


def _stream_unless_fitted(inputs, out: Path, log: list[dict]) -> int | None:
    """None when the take's detections are all cached and its fit is done (only the export may be left:
    the stages run one by one, each skipping what is done; ``log`` gets the detect entry); otherwise the
    number of requested frames, to be run as a stream (:mod:`capture.run.stream`)."""
    from capture.detector import LandmarkTrack
    from capture.run.stages import fit_dir_for, fit_is_done, fit_key
    from capture.run.stream import plan_detection

    det = inputs.detector
    cfg = inputs.config
    query = inputs.landmark_points if det.spec.kind == "query" else None
    frames = None if cfg.frames is None else range(*inputs.frame_range)
    plan = plan_detection(cfg.video, det, out, frames, det._check_query(query))
    if plan.groups:
        return len(plan.wanted)
    entry: list[dict] = []
    detect_stage(inputs, out, log=entry, progress=False)
    track = LandmarkTrack.load_npz(out / LANDMARKS)
    key = fit_key(inputs, track)
    if not track.face_found.any() or fit_is_done(fit_dir_for(out, key), key):
        log.extend(entry)
        return None
    return len(plan.wanted)


def export_options(cfg):
    """The exporters' options of a run (the overlay's layers from ``--overlay``)."""
    from capture.export import ExportOptions

    layers = getattr(cfg, "overlay", None)
    return ExportOptions() if layers is None else ExportOptions(overlay_layers=tuple(layers))


def rig_and_features(actor, formats) -> dict:
    """``ExportContext`` fields from the actor: its blend-shape rig when ``curves`` is exported, the
    template's feature lines (lids, lips, brows) when the overlay is."""
    if "curves" not in formats and "overlay" not in formats:
        return {}
    from capture.export.features import face_features

    rig = actor.face_rig()
    out = {"rig": rig} if "curves" in formats else {}
    if "overlay" in formats:
        out["features"] = face_features(actor.template_faces, actor.template_vertices, rig.expressions, rig.names)
    return out


def html_report(out: Path, report: dict, fit_dir: Path, actor, rows: list[dict], error_key: str, unit: str,
                fps: float, detections: dict | None = None, video: Path | None = None, camera=None,
                image_size: tuple[int, int] | None = None, figure_process=None, collector=None,
                images: dict | None = None, submitted=None, fits: dict | None = None) -> Path:
    """``OUT/report.html`` (:mod:`capture.export.report_html`): the take's plots and its worst frames.

    ``figure_process`` (:class:`capture.export.report_figures.FigureProcess`) draws the plots while the
    thumbnails are drawn here (None: both here); ``collector`` (:class:`capture.export.report_html.
    SeriesCollector`) has seen the take's fits already (None: they are read from ``fit_dir``); ``images``
    holds the worst frames' images that the stream kept (the others are read from ``video``); ``submitted``
    is the take's series, already given to ``figure_process`` (the stream's, ``stream_take(on_exported=)``);
    ``fits`` the worst frames' fits that the stream kept (else they are read from ``fit_dir``)."""
    from capture.export.features import face_features
    from capture.export.overlay_draw import FrameRenderer, Topology
    from capture.export.report_html import take_series, thumbnails, worst_frames, write_report_html
    from capture.run.stages import fits_at

    rig = actor.face_rig()
    errors = {int(r["frame"]): r.get(error_key) for r in rows}
    if submitted is not None and figure_process is not None:
        series = submitted
    else:
        series = (collector.series(fps, rig.names, errors, unit, detections) if collector is not None else
                  take_series(iter_fits(fit_dir), fps, rig.names, errors, unit, detections))
        if figure_process is not None:
            figure_process.submit(series)
    thumbs = []
    if video is not None and camera is not None and image_size is not None:
        worst = worst_frames(series)
        faces = actor.template_faces
        feats = face_features(faces, actor.template_vertices, rig.expressions, rig.names)
        renderer = FrameRenderer(Topology.of(faces, feats), camera, image_size, fps,
                                 ("mesh", "contours", "landmarks"))   # the caption says frame and error
        kept = fits if fits is not None and all(int(i) in fits for i in worst) else fits_at(fit_dir, worst,
                                                                                            THUMBNAIL_FIELDS)
        thumbs = thumbnails(video, worst, kept, detections or {}, renderer, images=images)
    figs = figure_process.result() if figure_process is not None else None
    return write_report_html(out, report, series, thumbs, figs)


def fits_key(out: Path, inputs, track) -> str:
    from capture.run.stages import fit_key

    return digest(fit_key(inputs, track))


def base_report(command: str, out: Path, settings: dict, log: list[dict], t_start: float) -> dict:
    return {"format": "capture-report", "version": 1, "command": command, "out_dir": str(out),
            "versions": versions(), "machine": machine(), "settings": settings, "stages": log,
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
        ["report.json", "report.html"]
    report["output_files"] = files
    write_report(out, report)
