"""What a detector did on a video, in numbers (pure functions over a :class:`~.pipeline.LandmarkTrack`).

* **Faces**: frames with a face, and the longest run of frames without one.
* **Confidence**: percentiles of the per-landmark confidence over face frames and the fraction below
  0.5 (the tracker's threshold); likewise the presence score.
* **Jitter** (per landmark, frame px): from frame-to-frame differences ``d_t = p_t - p_{t-1}`` over
  consecutive face frames, ``step_rms = sqrt(mean |d_t|^2)``: how far a landmark moves per frame,
  motion plus noise. The second difference ``a_t = p_{t+1} - 2 p_t + p_{t-1}`` cancels motion that is
  steady over three frames, and for independent per-frame noise of RMS ``r`` (2D) ``E |a|^2 = 6 r^2``;
  so ``noise_rms = sqrt(mean |a_t|^2 / 6)`` estimates the noise itself (exact on still footage,
  an upper bound when the face accelerates). With a confidence output only landmark-frames with
  confidence >= 0.5 count (an occluded landmark's guess is not jitter).
"""

from __future__ import annotations

import numpy as np

PERCENTILES = (5, 25, 50, 75, 95)
CONFIDENT = 0.5   # the tracker's threshold (TrackOptions.min_confidence)


def _pct(v: np.ndarray) -> dict:
    v = v[np.isfinite(v)]
    if v.size == 0:
        return {}
    return {f"p{p}": float(np.percentile(v, p)) for p in PERCENTILES} | {"mean": float(v.mean())}


def landmark_jitter(points: np.ndarray, valid: np.ndarray, frame_index: np.ndarray | None = None) -> dict:
    """Per-landmark jitter (frame px) of points (T, L, 2).

    ``valid`` (T,) or (T, L): which frames (or landmark-frames) count, e.g. face frames with a confident
    landmark; a difference counts when all its frames are valid and consecutive. Returns ``step_rms``
    (L,), ``noise_rms`` (L,) (NaN where there are none) and the numbers of differences used per landmark.
    """
    p = np.asarray(points, np.float64)
    t, count = p.shape[:2]
    ok = np.asarray(valid, bool)
    ok = np.broadcast_to(ok[:, None], (t, count)) if ok.ndim == 1 else ok
    ok = ok & np.isfinite(p).all(axis=2)
    fi = np.arange(t) if frame_index is None else np.asarray(frame_index)
    cons = (np.diff(fi) == 1)[:, None]
    pair = ok[1:] & ok[:-1] & cons                                     # (T-1, L)
    trip = pair[1:] & pair[:-1]                                        # (T-2, L)
    d2 = np.where(pair, np.sum((p[1:] - p[:-1]) ** 2, axis=2), 0.0)
    a2 = np.where(trip, np.sum((p[2:] - 2 * p[1:-1] + p[:-2]) ** 2, axis=2), 0.0)
    n1, n2 = pair.sum(axis=0), trip.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        step = np.where(n1 > 0, np.sqrt(d2.sum(axis=0) / np.maximum(n1, 1)), np.nan)
        noise = np.where(n2 > 0, np.sqrt(a2.sum(axis=0) / np.maximum(n2, 1) / 6.0), np.nan)
    return {"step_rms": step, "noise_rms": noise, "pairs": n1, "triples": n2}


def longest_gap(face: np.ndarray) -> int:
    best = cur = 0
    for f in np.asarray(face, bool):
        cur = 0 if f else cur + 1
        best = max(best, cur)
    return best


def summarise(track, worst: int = 5) -> dict:
    """A JSON-ready summary of a track (see the module docstring)."""
    face = np.asarray(track.face_found, bool)
    n = len(face)
    count = track.points.shape[1]
    out: dict = {"detector": track.detector, "frames": n, "frames_with_face": int(face.sum()),
                 "face_fraction": float(face.mean()) if n else 0.0, "longest_gap_frames": longest_gap(face),
                 "image_size": list(track.image_size), "fps": track.fps}
    if track.confidence is not None:
        c = np.asarray(track.confidence)[face]
        out["confidence"] = _pct(c.reshape(-1)) | {
            "below_0.5": float(np.mean(c < CONFIDENT)) if c.size else None}
    if track.presence is not None:
        out["presence"] = _pct(np.asarray(track.presence, np.float64)[face])
    valid = np.broadcast_to(face[:, None], track.points.shape[:2])
    if track.confidence is not None:   # only confident landmarks: an occluded one's guess is not jitter
        valid = valid & (np.nan_to_num(np.asarray(track.confidence), nan=0.0) >= CONFIDENT)
    j = landmark_jitter(track.points, valid, track.frame_index)
    for key in ("step_rms", "noise_rms"):
        v = j[key]
        fin = np.isfinite(v)
        entry = {"median": float(np.median(v[fin])) if fin.any() else None,
                 "p95": float(np.percentile(v[fin], 95)) if fin.any() else None,
                 "max": float(v[fin].max()) if fin.any() else None}
        if key == "noise_rms" and fin.any():
            order = np.argsort(-np.where(fin, v, -np.inf))[:worst]
            entry["worst_landmarks"] = [{"landmark": int(i), "px": float(v[i])} for i in order if fin[i]]
        out[f"jitter_{key}_px"] = entry
    out["jitter_pairs_median"] = float(np.median(j["pairs"])) if count else 0.0
    out["per_landmark"] = {"step_rms_px": [None if not np.isfinite(x) else round(float(x), 5) for x in j["step_rms"]],
                           "noise_rms_px": [None if not np.isfinite(x) else round(float(x), 5) for x in j["noise_rms"]]}
    return out
