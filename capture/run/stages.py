"""The stages of ``capture run``: detect, fit, export. Each skips the work that is already done.

Every stage has the form ``stage(inputs, ..., out_dir, overwrite=False, log=None) -> Path`` and appends
one entry ``{"stage", "status": "done" | "skipped", "seconds", ...}`` to ``log``:

* **detect** (``detections/track.npz``): :func:`capture.detector.detect_video` with its per-segment cache in
  ``OUT/detections/<key>/`` (the key covers the detector, its spec, the tracking and the video).
* **fit** (``fit/<key>/done.json`` and ``frames_<first>.npz`` chunks): the key hashes the fit settings, window, device, the landmarks,
  weights and face flags fed to the fit, the camera, the actor's weights and the landmark embedding;
  ``fit_take`` keeps finished windows in ``fit/<key>/windows/`` so an interrupted fit resumes.
* **export** (``export.json``): the key hashes the fit key, the formats and the frame rate; the
  writers' files are listed there. Writers are aborted on any error or interrupt.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, Sequence

import numpy as np

from capture.io.atomic import write_json
from capture.io.rows import BLOCK_FRAMES
from capture.run.progress import StageProgress
from capture.run.store import Blocks, array_digest, digest, load_frame_fits, read_json, save_frame_fits

LANDMARKS = "detections/track.npz"
EXPORT_JSON = "export.json"


def _log(log: list | None, entry: dict) -> None:
    if log is not None:
        log.append(entry)


# ------------------------------------------------------------------------------------------ detect
def detect_stage(inputs, out_dir: Path, overwrite: bool = False, log: list | None = None,
                 progress: bool = True) -> Path:
    """Landmarks of the requested frames -> ``OUT/detections/track.npz`` (points, confidence, face flags, crops)."""
    from capture.detector import LandmarkTrack, detect_video

    t0 = time.perf_counter()
    det = inputs.detector
    start, end = inputs.frame_range
    query = inputs.landmark_points if det.spec.kind == "query" else None
    # Without --frames every frame the video really has (its header's count can be an overestimate).
    frames = None if inputs.config.frames is None else range(start, end)
    track = detect_video(inputs.config.video, det, cache_dir=out_dir, frames=frames, progress=progress,
                         query_points=query)
    path = Path(out_dir) / LANDMARKS
    new = array_digest(track.frame_index, track.points, track.confidence, track.face_found)
    old = None
    if path.is_file() and not overwrite:
        try:
            o = LandmarkTrack.load_npz(path)
            old = array_digest(o.frame_index, o.points, o.confidence, o.face_found)
        except Exception:
            old = None
    if old != new:
        track.save_npz(path)
    _log(log, {"stage": "detect", "status": "skipped" if track.detected_frames == 0 else "done",
               "seconds": time.perf_counter() - t0, "frames": len(track), "frames_detected": track.detected_frames,
               "frames_cached": track.cached_frames, "faces_found": int(track.face_found.sum())})
    return path


def landmark_weights(track, frames: slice = slice(None)) -> np.ndarray:
    """Per-landmark fit weights (T, L) of the track's ``frames``: the detector's confidence (1 without
    one), 0 where missing."""
    points = track.points[frames]
    w = np.ones(points.shape[:2]) if track.confidence is None else np.asarray(track.confidence[frames], np.float64)
    ok = np.isfinite(points).all(-1) & np.isfinite(w)
    out = np.clip(w, 0.0, 1.0)
    out[~ok] = 0.0
    return out


def landmark_weight_blocks(track) -> Blocks:
    """:func:`landmark_weights` of the whole track, ``BLOCK_FRAMES`` frames at a time (for a digest)."""
    n, count = track.points.shape[:2]
    return Blocks(np.float64, (n, count), lambda: (landmark_weights(track, slice(k, k + BLOCK_FRAMES))
                                                   for k in range(0, n, BLOCK_FRAMES)))


# --------------------------------------------------------------------------------------------- fit
def fit_key(inputs, track) -> dict:
    cam = inputs.camera.camera
    cfg = inputs.config
    key = {"fit_settings": inputs.fit_settings.to_dict(), "window": cfg.window, "overlap": cfg.overlap,
           "device": cfg.device, "actor_weights_sha256": inputs.actor_weights_sha256,
           "embedding_sha256": inputs.embedding_sha256,
           "camera": {"K": cam.K.tolist(), "dist": cam.dist.tolist(), "image_size": list(cam.image_size)},
           "landmarks_sha256": array_digest(track.frame_index, track.points, landmark_weight_blocks(track),
                                            track.face_found),
           "stored": "mesh maps"}    # meshes stored as maps of the actor's features where they are (store.MESH_BASIS)
    if getattr(cfg, "segments", None):   # stitched from segments by capture batch: another fit
        key["segments"] = [[int(s), int(e)] for s, e in cfg.segments]
    return key


def fit_dir_for(out_dir: Path, key: dict) -> Path:
    return Path(out_dir) / "fit" / digest(key)[:16]


def _frame_fit_class():
    from capture.fit.records import FrameFit

    return FrameFit


FIT_CHUNK = 64   # frames per stored chunk of frame fits
DONE_JSON = "done.json"


def fit_is_done(fit_dir: Path, key: dict) -> bool:
    done = read_json(Path(fit_dir) / DONE_JSON)
    return (done is not None and done.get("key") == key
            and all((Path(fit_dir) / c).is_file() for c in done.get("chunks", [])))


def fit_frames(fit_dir: Path) -> list[int]:
    """Video frame numbers of a finished fit, ascending."""
    return [int(i) for i in read_json(Path(fit_dir) / DONE_JSON)["frames"]]


def iter_fits(fit_dir: Path, fields: Iterable[str] | None = None) -> Iterator[Any]:
    """The frame fits of a finished fit, in frame order, one chunk in memory at a time (``fields``: only
    these are read, e.g. not the meshes; the others are None)."""
    cls = _frame_fit_class()
    for chunk in read_json(Path(fit_dir) / DONE_JSON)["chunks"]:
        yield from load_frame_fits(Path(fit_dir) / chunk, cls, fields)


def fits_at(fit_dir: Path, frames: Iterable[int], fields: Iterable[str] | None = None) -> dict[int, Any]:
    """The frame fits of ``frames`` (video frame numbers) of a finished fit, reading only the chunks that
    hold them (a chunk ``frames_<first>.npz`` holds frames from ``first`` to the next chunk's first) and,
    with ``fields``, only those members (the others are None)."""
    want = {int(i) for i in frames}
    chunks = read_json(Path(fit_dir) / DONE_JSON)["chunks"]
    firsts = [int(Path(c).stem.split("_")[-1]) for c in chunks]
    need = sorted({max((k for k, f in enumerate(firsts) if f <= i), default=0) for i in want}) if chunks else []
    cls = _frame_fit_class()
    return {int(f.frame): f for k in need for f in load_frame_fits(Path(fit_dir) / chunks[k], cls, fields)
            if int(f.frame) in want}


def run_fit_cached(fit_dir: Path, key: dict, total: int, start_fit: Callable[[Path], Iterator[Any]],
                   label: str, progress: bool, log: list | None, overwrite: bool = False,
                   frame_map: np.ndarray | None = None, basis: Callable[[], np.ndarray] | None = None) -> Path:
    """Shared by run and fit3d: skip when ``fit_dir/done.json`` matches ``key``, else fit (resumable).

    The fit streams: every :data:`FIT_CHUNK` frames are stored as ``frames_<first>.npz``; ``done.json``
    (key, chunks, frames) is written last. ``frame_map[j]`` is the video frame of take position ``j``
    (``FrameFit.frame`` counts from the first fitted frame); stored fits carry video frame numbers.
    ``basis()``: the actor's features, asked for once a fit has a mesh map: frames whose meshes it makes are
    stored without their vertices (:func:`capture.run.store.save_frame_fits`).
    """
    from dataclasses import replace

    t0 = time.perf_counter()
    fit_dir = Path(fit_dir)
    if not overwrite and fit_is_done(fit_dir, key):
        _log(log, {"stage": "fit", "status": "skipped", "seconds": time.perf_counter() - t0,
                   "frames": len(fit_frames(fit_dir)), "fit_dir": str(fit_dir)})
        return fit_dir
    write_json(fit_dir / "key.json", key)
    chunks: list[str] = []
    frames: list[int] = []
    pending: list[Any] = []

    made: list[np.ndarray] = []

    def flush() -> None:
        if pending:
            name = f"frames_{int(pending[0].frame):06d}.npz"
            if basis is not None and not made and getattr(pending[0], "mesh_map", None) is not None:
                made.append(basis())
            save_frame_fits(fit_dir / name, pending, made[0] if made else None)
            chunks.append(name)
            pending.clear()

    with StageProgress(label, total, progress) as bar:
        for ff in start_fit(fit_dir / "windows"):
            if frame_map is not None:
                ff = replace(ff, frame=int(frame_map[int(ff.frame)]))
            pending.append(ff)
            frames.append(int(ff.frame))
            if len(pending) == FIT_CHUNK:
                flush()
            bar.advance(1)
    flush()
    write_json(fit_dir / DONE_JSON, {"key": key, "chunks": chunks, "frames": frames})
    _log(log, {"stage": "fit", "status": "done", "seconds": time.perf_counter() - t0, "frames": len(frames),
               "fit_dir": str(fit_dir)})
    return fit_dir


def take_landmarks(inputs, track):
    """The fit's view of a detected track (:class:`capture.fit.take.TakeLandmarks`)."""
    from capture.fit.take import TakeLandmarks

    return TakeLandmarks(track.points, landmark_weights(track), track.face_found, inputs.landmark_points)


def windowed_fit(inputs, cache: Path | None):
    """The run's fit settings, windows, device and threads (:class:`capture.fit.take.WindowedFit`)."""
    from capture.fit.records import WindowedFit

    cfg = inputs.config
    return WindowedFit(inputs.fit_settings, cfg.window, cfg.overlap, cache, cfg.device, cfg.threads)


def fit_stage(inputs, track, out_dir: Path, overwrite: bool = False, log: list | None = None,
              progress: bool = True) -> Path:
    """Fit the actor to the landmarks (``fit_take``) -> ``OUT/fit/<key>/`` (see :func:`run_fit_cached`)."""
    key = fit_key(inputs, track)
    fdir = fit_dir_for(out_dir, key)

    def start(cache: Path):
        from capture.fit.take import fit_take

        return fit_take(inputs.actor, take_landmarks(inputs, track), inputs.camera.camera,
                        windowed_fit(inputs, cache))

    def basis():
        from capture.fit.take import query_template
        from models.fit_state import mesh_basis

        return mesh_basis(query_template(inputs.actor, inputs.config.device))

    return run_fit_cached(fdir, key, len(track), start, "fit", progress, log, overwrite,
                          frame_map=track.frame_index, basis=basis)


# ------------------------------------------------------------------------------------------ export
def export_stage(fit_dir: Path, context: Any, formats: Sequence[str], key: dict, out_dir: Path,
                 images: Callable[[Sequence[int]], Iterable[tuple[int, np.ndarray]]] | None = None,
                 detections: dict[int, Any] | None = None, overwrite: bool = False, log: list | None = None,
                 progress: bool = True) -> Path:
    """Write every requested format -> ``OUT/export.json`` (the key and the files written).

    ``fit_dir`` holds a finished fit (:func:`iter_fits`, streamed: one chunk in memory at a time);
    ``images(frame_indices)`` yields ``(index, BGR frame)`` in ascending order for the overlay;
    ``detections`` maps a frame to its detected landmarks (passed to the writers beside the fit).
    ``context`` is a :class:`capture.export.base.ExportContext`; its ``options.overwrite`` is set here:
    per-frame files of an interrupted export of the same fit are kept, those of another fit replaced.
    """
    from dataclasses import replace

    from capture.export import EXPORTERS, open_exporters

    t0 = time.perf_counter()
    out_dir = Path(out_dir)
    state_path = out_dir / EXPORT_JSON
    state = read_json(state_path)
    if (not overwrite and state is not None and state.get("key") == key and state.get("status") == "done"
            and all((out_dir / f).exists() for f in state.get("files", []))):
        _log(log, {"stage": "export", "status": "skipped", "seconds": time.perf_counter() - t0,
                   "files": len(state["files"])})
        return state_path
    # The per-frame files on disk were all made with `key` only if a finished export of `key` made them, or an
    # interrupted one that started from such files; the key is recorded as "key" only after the files it
    # describes are written (a resumed export after a settings change rewrites every frame).
    state = state or {}
    files_key = state.get("key") if state.get("status") == "done" else state.get("files_key")
    same_fit = files_key == key
    context = replace(context, options=replace(context.options, overwrite=overwrite or not same_fit))
    previous = set(state.get("files", [])) | set(state.get("previous_files", []))
    write_json(state_path, {"status": "running", "writing": key, "files_key": key if same_fit and not overwrite
                            else None, "files": [], "previous_files": sorted(previous)})

    frames = fit_frames(fit_dir)
    want_images = images is not None and any(EXPORTERS[f].needs_image for f in formats)
    with open_exporters(formats, out_dir, context) as writers:
        source = iter(images(frames)) if want_images else None
        with StageProgress("export", len(frames), progress) as bar:
            for ff in iter_fits(fit_dir):
                image = None
                for index, img in source if source is not None else ():
                    if int(index) == int(ff.frame):
                        image = img
                        break
                writers.write(ff, image, None if detections is None else detections.get(int(ff.frame)))
                bar.advance(1)
    files = writers.paths
    rel = sorted({str(Path(f).resolve().relative_to(out_dir.resolve())) for f in files})
    for stale in sorted(previous - set(rel)):  # files of an earlier export that this one did not write
        p = out_dir / stale
        if p.is_file():
            p.unlink()
    write_json(state_path, {"key": key, "status": "done", "files": rel})
    _log(log, {"stage": "export", "status": "done", "seconds": time.perf_counter() - t0, "files": len(rel)})
    return state_path
