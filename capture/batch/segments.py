"""Long takes of ``capture batch`` split into segments of frames, fitted as separate tasks and blended.

With ``segment_frames = S`` (``[shoot]`` or ``--segment-frames``), a take of more than ``S`` frames
is cut into segments of at most ``S`` frames that share ``O`` frames with their neighbours (``O`` =
the take's fitting window, 30 frames by default, so each segment sees a whole window of context at
its seams). Every segment is one Ray task (:func:`fit_segment`):

* **detect** its frames into the take's own detection cache (``OUT/detections/<key>/``): the
  detector's 32-frame tracking segments are independent and aligned to absolute frame numbers, so
  the landmarks are exactly those of an unsplit run;
* **fit** them with ``fit_take`` like ``capture run`` does (cold start at the segment's first
  window), into ``OUT/fit/segments/<key>/`` (resumable, the same chunked store).

A last task per take (:func:`merge_segments`) stitches the segments into the take's fit
(``OUT/fit/<key>/``, the key of ``capture run`` for these landmarks and settings plus the segments, so
neither ``capture run`` nor an unsplit batch takes it for an unsplit fit): frames of one
segment are taken as they are; in an overlap every per-frame output is the smoothstep blend from
the earlier to the later segment (rotations re-orthonormalised, as at the window seams of
:mod:`capture.fit.take`; frame codes, which live in each segment's own latent space, are the nearer
segment's), and the reprojection error of a blended frame is measured again. Then
:func:`capture.run.take.run_take` finds detection and fit done and exports and reports as usual: the
run folder has the same layout as ``capture run``'s, and ``report.json`` lists the segments.

The cost is ``O / (S - O)`` more frames fitted and a cold start per segment; the gain is that one
long take spreads over all workers.
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path
from typing import Any, Iterator, Sequence

import numpy as np

from capture.fit.records import repeated_rows
from capture.io.errors import CaptureError
from capture.run.inputs import RunConfig


def plan_segments(start: int, end: int, size: int, overlap: int) -> list[tuple[int, int]]:
    """Segments ``[(s, e), ...]`` covering frames ``[start, end)``: at most ``size`` frames each, consecutive
    ones sharing ``overlap`` frames, lengths as even as possible; one segment when the range fits.

    >>> plan_segments(0, 100, 40, 10)
    [(0, 40), (30, 70), (60, 100)]
    """
    n = end - start
    if size <= 0 or n <= size:
        return [(start, end)]
    if overlap < 0 or 2 * overlap >= size:
        raise ValueError(f"segment size {size} must exceed twice the overlap {overlap}")
    count = math.ceil((n - overlap) / (size - overlap))
    starts = [start + round(k * (n - overlap) / count) for k in range(count)]
    return [(s, (starts[k + 1] + overlap) if k + 1 < count else end) for k, s in enumerate(starts)]


def _smoothstep(x: float) -> float:
    return x * x * (3 - 2 * x)


#: FrameFit fields blended across a seam (the rest come from the nearer segment).
BLENDED = ("head_R", "head_t", "jaw_R", "jaw_t", "coefficients_landmarks", "vertices", "landmarks_fit")


def blend_frame(a: Any, b: Any, alpha: float) -> Any:
    """``(1 - alpha) * a + alpha * b`` of two fits of one frame (:data:`BLENDED` fields; rotations
    re-orthonormalised by :func:`capture.fit.take._blend`); other fields from ``b`` when ``alpha >= 0.5``."""
    from capture.fit.take import _blend

    mixed = _blend({k: np.asarray(getattr(a, k)) for k in BLENDED}, {k: np.asarray(getattr(b, k)) for k in BLENDED},
                   0, alpha)
    mixed["coefficients_landmarks"] = repeated_rows(mixed["coefficients_landmarks"])
    near = b if alpha >= 0.5 else a
    return replace(near, **mixed)


def reprojection_rms(landmarks_fit: np.ndarray, points: np.ndarray, weights: np.ndarray) -> float:
    """RMS (px) over the landmarks the fit used (weight > 0, finite), as ``fit_take`` measures it; NaN if none."""
    ok = (weights > 0) & np.isfinite(points).all(1)
    if not ok.any():
        return float("nan")
    r = np.asarray(landmarks_fit)[ok] - points[ok]
    return float(np.sqrt((r ** 2).sum(1).mean()))


def stitch(segments: Sequence[tuple[int, int]], fits: Sequence[Iterator[Any]]) -> Iterator[tuple[Any, bool]]:
    """Per-frame fits of consecutive overlapping segments -> ``(fit, blended)`` once per frame, in order.

    ``fits[k]`` yields segment ``k``'s fits in frame order (``.frame``: video frame numbers). In the
    overlap of segments ``k`` and ``k + 1`` the blend weight of ``k + 1`` is ``smoothstep((i + 1) / (O + 1))``
    at the overlap's ``i``-th frame.
    """
    held: dict[int, Any] = {}
    for k, ((s, e), seg) in enumerate(zip(segments, fits)):
        n_ov = max(0, segments[k - 1][1] - s) if k else 0
        next_start = segments[k + 1][0] if k + 1 < len(segments) else None
        keep: dict[int, Any] = {}
        for f in seg:
            i = int(f.frame)
            if i in held:
                f, mixed = blend_frame(held.pop(i), f, _smoothstep((i - s + 1) / (n_ov + 1))), True
            else:
                mixed = False
            if next_start is not None and i >= next_start:
                keep[i] = f
                continue
            yield f, mixed
        if held:
            raise RuntimeError(f"segment {s}:{e} lacks frames {sorted(held)[:3]} of its overlap")
        held = keep
    for i in sorted(held):   # no later segment (cannot happen with plan_segments): as they are
        yield held[i], False


# ------------------------------------------------------------------------------------------ tasks
def _segment_dir(out: Path, key: dict) -> Path:
    from capture.run.store import digest

    return Path(out) / "fit" / "segments" / digest(key)[:16]


def _segment_track(inputs, start: int, end: int):
    from capture.detector import detect_video

    det = inputs.detector
    query = inputs.landmark_points if det.spec.kind == "query" else None
    return detect_video(inputs.config.video, det, cache_dir=inputs.out, frames=range(start, end), progress=False,
                        query_points=query)


def _segment_key(inputs, track, start: int, end: int) -> dict:
    from capture.run.stages import fit_key

    return {**fit_key(inputs, track), "segment": [int(start), int(end)]}


def _claim(inputs) -> None:
    """Claim the take's folder like ``capture run`` (a placeholder ``run.json`` until the merge writes it)."""
    from capture.run.store import RUN_JSON, claim_run_dir, write_run_json

    label = f"{Path(inputs.config.video).name} (id {inputs.video_id[:12]})"
    claim_run_dir(inputs.out, inputs.video_id, label, inputs.config.overwrite)
    if not (inputs.out / RUN_JSON).is_file():
        write_run_json(inputs.out, inputs.video_id, label, {"segmented": True}, {}, "running")


def fit_segment(cfg: RunConfig, start: int, end: int) -> dict:
    """Detect and fit frames ``[start, end)`` of a take into ``OUT/fit/segments/<key>/`` (skipped when done)."""
    from capture.fit.take import fit_take
    from capture.run.inputs import resolve_inputs
    from capture.run.stages import run_fit_cached, take_landmarks, windowed_fit

    inputs = resolve_inputs(cfg)
    _claim(inputs)
    track = _segment_track(inputs, start, end)
    if not track.face_found.any():
        raise CaptureError(f"no face found in frames {start}:{end} (a whole segment); run this take without "
                           f"segment_frames or with longer segments")
    key = _segment_key(inputs, track, start, end)

    def run(cache: Path):
        return fit_take(inputs.actor, take_landmarks(inputs, track), inputs.camera.camera,
                        windowed_fit(inputs, cache))

    fdir = run_fit_cached(_segment_dir(inputs.out, key), key, len(track), run, "fit", False, None,
                          frame_map=track.frame_index)
    return {"segment": [start, end], "fit_dir": str(fdir), "frames_fitted": len(track)}


def merge_segments(cfg: RunConfig, segments: Sequence[tuple[int, int]]) -> dict:
    """Stitch the fitted segments into the take's fit, then export and report with ``run_take``."""
    from capture.detector import LandmarkTrack
    from capture.run.take import run_take
    from capture.run.inputs import resolve_inputs
    from capture.run.report import write_report
    from capture.run.stages import (LANDMARKS, detect_stage, fit_dir_for, fit_is_done, fit_key, iter_fits,
                                    landmark_weights, run_fit_cached)

    cfg = replace(cfg, segments=tuple((int(s), int(e)) for s, e in segments))   # in the fit's key
    inputs = resolve_inputs(cfg)
    _claim(inputs)
    detect_stage(inputs, inputs.out, progress=False)          # every detection segment is cached by now
    track = LandmarkTrack.load_npz(inputs.out / LANDMARKS)
    key = fit_key(inputs, track)
    fdir = fit_dir_for(inputs.out, key)
    dirs = []
    seg_inputs = replace(inputs, config=replace(cfg, segments=None))   # each segment is a plain fit
    for s, e in segments:
        seg_track = _segment_track(inputs, s, e)
        skey = _segment_key(seg_inputs, seg_track, s, e)
        d = _segment_dir(inputs.out, skey)
        if not fit_is_done(d, skey):
            raise RuntimeError(f"segment {s}:{e} of the take is not fitted (its task failed?)")
        dirs.append(d)
    row = {int(i): j for j, i in enumerate(track.frame_index)}
    weights = landmark_weights(track)
    n_blended = 0

    def stitched(_cache: Path):
        nonlocal n_blended
        for f, mixed in stitch(segments, [iter_fits(d) for d in dirs]):
            if mixed:
                j = row[int(f.frame)]
                f = replace(f, reprojection_rms_px=reprojection_rms(f.landmarks_fit, track.points[j], weights[j]))
                n_blended += 1
            yield f

    merged = not fit_is_done(fdir, key)
    if merged:
        run_fit_cached(fdir, key, len(track), stitched, "merge", False, None)
    report = run_take(cfg)
    for st in report["stages"]:   # run_take found them done: by the segment tasks, just now
        if merged and st["stage"] in ("detect", "fit") and st["status"] == "skipped":
            st["status"] = f"done in {len(segments)} segments"
    report["segments"] = {"frames": [list(se) for se in segments], "overlap": segments[0][1] - segments[1][0]
                          if len(segments) > 1 else 0, "blend": "smoothstep over each overlap",
                          "segment_fit_dirs": [str(d) for d in dirs]}
    write_report(inputs.out, report)
    return report
