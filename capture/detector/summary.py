"""What a detector did on a video, in numbers (pure functions over a :class:`~.pipeline.LandmarkTrack`).

* **Faces**: frames with a face, and the longest run of frames without one.
* **Confidence**: percentiles of the per-landmark confidence over face frames and the fraction below
  0.5 (the tracker's threshold); likewise the presence score.
* **Jitter** (per landmark, frame px): from frame-to-frame differences ``d_t = p_t - p_{t-1}`` over
  consecutive face frames, ``step_rms = sqrt(mean |d_t|^2)``: how far a landmark moves per frame,
  motion plus noise. The second difference ``a_t = p_{t+1} - 2 p_t + p_{t-1}`` cancels motion that is
  steady over three frames, and for independent per-frame noise of RMS ``r`` (2D) ``E |a|^2 = 6 r^2``;
  so ``noise_rms = sqrt(mean |a_t|^2 / 6)`` estimates the noise itself (exact on still footage,
  an upper bound when the face accelerates).
"""

from __future__ import annotations

import numpy as np

PERCENTILES = (5, 25, 50, 75, 95)


def _pct(v: np.ndarray) -> dict:
    v = v[np.isfinite(v)]
    if v.size == 0:
        return {}
    return {f"p{p}": float(np.percentile(v, p)) for p in PERCENTILES} | {"mean": float(v.mean())}


def landmark_jitter(points: np.ndarray, face: np.ndarray, frame_index: np.ndarray | None = None) -> dict:
    """Per-landmark jitter (frame px) of points (T, L, 2); only runs of consecutive face frames count.

    Returns ``step_rms`` (L,), ``noise_rms`` (L,) (NaN where there are too few frames) and the numbers of
    differences used.
    """
    p = np.asarray(points, np.float64)
    t, count = p.shape[:2]
    ok = np.asarray(face, bool) & np.isfinite(p).all(axis=(1, 2))
    fi = np.arange(t) if frame_index is None else np.asarray(frame_index)
    pair = ok[1:] & ok[:-1] & (np.diff(fi) == 1)
    d = p[1:] - p[:-1]
    n1 = int(pair.sum())
    step = np.sqrt((np.sum(d ** 2, axis=2)[pair]).mean(axis=0)) if n1 else np.full(count, np.nan)
    trip = pair[1:] & pair[:-1]
    a = p[2:] - 2 * p[1:-1] + p[:-2]
    n2 = int(trip.sum())
    noise = np.sqrt((np.sum(a ** 2, axis=2)[trip]).mean(axis=0) / 6.0) if n2 else np.full(count, np.nan)
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
    out: dict = {"detector": track.detector, "frames": n, "frames_with_face": int(face.sum()),
                 "face_fraction": float(face.mean()) if n else 0.0, "longest_gap_frames": longest_gap(face),
                 "image_size": list(track.image_size), "fps": track.fps}
    if track.confidence is not None:
        c = np.asarray(track.confidence)[face]
        out["confidence"] = _pct(c.reshape(-1)) | {
            "below_0.5": float(np.mean(c < 0.5)) if c.size else None}
    if track.presence is not None:
        out["presence"] = _pct(np.asarray(track.presence, np.float64)[face])
    j = landmark_jitter(track.points, face, track.frame_index)
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
    out["jitter_pairs"], out["jitter_triples"] = j["pairs"], j["triples"]
    out["per_landmark"] = {"step_rms_px": [None if not np.isfinite(x) else round(float(x), 5) for x in j["step_rms"]],
                           "noise_rms_px": [None if not np.isfinite(x) else round(float(x), 5) for x in j["noise_rms"]]}
    return out
