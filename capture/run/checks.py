"""Plausibility checks of a run: nonsense that parses becomes a reported frame flag or a one-line error.

* :func:`check_detections` (before the fit): a frame whose landmarks collapse onto a point (a broken
  detector puts every landmark on one pixel) or that has too few landmarks with confidence above 0 is
  not fitted: its face flag is cleared and the report gives the reason. When no frame is left, one
  line says what is wrong with the detector's output.
* :func:`check_head_depths` (after the fit): every fitted frame's head depth (``head_t`` z, mm) must
  lie in :data:`DEPTH_RANGE_MM`. Frames outside get the flag ``head_depth_implausible`` in the report;
  when most frames are outside, the run is not a success (a wrong focal length, principal point or
  actor unit, never a real head 80 m away).

Pure functions of the track and the stored fits; thresholds are module constants.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from capture.io.errors import CaptureError
from capture.io.rows import BLOCK_FRAMES

#: Landmarks whose spread (RMS distance from their centroid, px) is below this have collapsed.
COLLAPSED_SPREAD_PX = 1.0
#: Fewest landmarks with confidence > 0 a frame needs to be fitted (a head pose needs 6 points).
MIN_LANDMARKS = 6
#: Plausible distance of a face from the camera along z (mm): 5 cm .. 20 m.
DEPTH_RANGE_MM = (50.0, 20000.0)
#: A run whose fitted frames are more often outside :data:`DEPTH_RANGE_MM` than this fraction fails.
MAX_IMPLAUSIBLE_FRACTION = 0.5


def landmark_problems(points: np.ndarray, confidence: np.ndarray | None) -> np.ndarray:
    """Per frame, ``""`` or why its landmarks cannot be fitted. ``points (T, L, 2)`` px, ``confidence (T, L)``."""
    out = np.full(len(points), "", dtype=object)
    for k in range(0, len(points), BLOCK_FRAMES):
        out[k:k + BLOCK_FRAMES] = _problems(points[k:k + BLOCK_FRAMES],
                                            None if confidence is None else confidence[k:k + BLOCK_FRAMES])
    return out


def _problems(points: np.ndarray, confidence: np.ndarray | None) -> np.ndarray:
    points = np.asarray(points, np.float64)
    usable = np.isfinite(points).all(-1)
    if confidence is not None:
        c = np.asarray(confidence, np.float64)
        usable &= np.isfinite(c) & (c > 0)
    out = np.full(len(points), "", dtype=object)
    for j in range(len(points)):
        p = points[j][usable[j]]
        if len(p) < MIN_LANDMARKS:
            out[j] = f"only {len(p)} landmarks with confidence > 0 (a fit needs {MIN_LANDMARKS})"
            continue
        spread = float(np.sqrt(((p - p.mean(0)) ** 2).sum(1).mean()))
        if spread < COLLAPSED_SPREAD_PX:
            out[j] = f"detector output collapsed: all landmarks within {spread:.2f} px of one point"
    return out


def check_detections(track, detector_name: str) -> dict[int, str]:
    """Clear ``track.face_found`` where the landmarks cannot be fitted; ``{frame: reason}`` of those frames.

    Raises CaptureError when frames had a face but none of them can be fitted.
    """
    problems = landmark_problems(track.points, track.confidence)
    bad = np.asarray(track.face_found, bool) & (problems != "")
    reasons = {int(track.frame_index[j]): f"{problems[j]} ({detector_name})" for j in np.flatnonzero(bad)}
    if bad.any() and not (np.asarray(track.face_found, bool) & ~bad).any():
        first = problems[np.flatnonzero(bad)[0]]
        raise CaptureError(f"detector {detector_name} found a face in {int(bad.sum())} frame(s) but none can be fitted "
                           f"({first}); check the detector's output decoding in its spec (docs/detector_spec.md)")
    track.face_found = np.asarray(track.face_found, bool) & ~bad
    return reasons


def head_depth(f) -> float | None:
    """A frame fit's head depth (``head_t`` z, mm) if the frame was fitted, else None."""
    t = getattr(f, "head_t", None)
    if t is None or str(getattr(f, "status", "fitted")) != "fitted":
        return None
    return float(np.asarray(t, np.float64).reshape(-1)[2])


def check_head_depths(fit_dir: Path, rows: list[dict], depths: dict[int, float] | None = None) -> str | None:
    """Flag report rows whose head depth is implausible; the error line when most fitted frames are.

    ``depths``: the fitted frames' :func:`head_depth` by frame, as a streamed run collects them; None: read
    from the fit in ``fit_dir``."""
    from capture.run.stages import iter_fits

    depth = depths
    if depth is None:
        depth = {int(f.frame): z for f in iter_fits(fit_dir, ("head_t", "status"))
                 if (z := head_depth(f)) is not None}
    lo, hi = DEPTH_RANGE_MM
    bad = []
    for r in rows:
        z = depth.get(int(r["frame"]))
        if z is None:
            continue
        r["head_depth_mm"] = z if np.isfinite(z) else None
        if not (np.isfinite(z) and lo <= z <= hi):
            r.setdefault("flags", []).append("head_depth_implausible")
            bad.append(z)
    if depth and len(bad) > MAX_IMPLAUSIBLE_FRACTION * len(depth):
        med = float(np.nanmedian(np.asarray(bad, np.float64))) if np.isfinite(bad).any() else float("nan")
        return (f"the fitted head is {med / 1000:.3g} m from the camera on {len(bad)} of {len(depth)} frames (a face "
                f"is {lo / 1000:g}-{hi / 1000:g} m away): check the camera file (focal length, principal point, "
                f"image size) and the actor's units; see report.json")
    return None
