"""The geometric check of one detection: every corner must agree with its neighbours on the board.

Over a few squares a lens maps the flat board almost exactly by a homography (distortion bends straight lines
only over larger distances), so each corner's position is predicted from the homography fitted to its detected
neighbours within ``radius`` squares (``cv2.findHomography``, least squares, at least 5 neighbours and no line
through all of them but one). A corner more than ``tolerance`` (0.2) of a local square away from its
prediction is inconsistent: a mis-identified marker, a corner snapped to the wrong saddle, a reflection. Such
corners are removed; when more than ``max_bad_fraction`` (25 %) of a view's checked corners, and more than
one, are inconsistent the whole detection is untrustworthy and the view is dropped. One corner alone never
condemns a view: in a partial view at the image's edge only a few corners have enough neighbours to be
checked, and one of 3 is already a third (a blurred corner of a strongly distorted image can be off by that
much; plain OpenCV keeps such views, and dropping one lost to it by 0.95 px, BENCHMARKS.md). Nor does it drop
a view by leaving it too few corners: a view of ``min_corners`` with one doubtful corner is kept whole, and a
corner a square off (a mis-read marker) then makes the view an outlier of the first solve
(:mod:`calib.calibrate`), which drops it. Corners with too few neighbours are kept unchecked (board edges,
partial views).
"""

from __future__ import annotations

import numpy as np

from calib.detect import Detection


def corner_inconsistency(detection: Detection, square_mm: float, radius: int = 2,
                         excluded: np.ndarray | None = None) -> np.ndarray:
    """(n,) distance of each corner from its neighbours' prediction, in local squares; NaN if unchecked.

    Corners flagged in ``excluded`` (n,) bool are not used as neighbours (nor checked).
    """
    import cv2

    obj = detection.object_points[:, :2].astype(np.float64) / square_mm  # board grid units
    img = detection.image_points.astype(np.float64)
    out = np.full(len(obj), np.nan)
    usable = np.ones(len(obj), bool) if excluded is None else ~excluded
    cheb = np.abs(obj[:, None, :] - obj[None, :, :]).max(2)
    for k in np.nonzero(usable)[0]:
        nb = np.nonzero((cheb[k] <= radius + 1e-6) & (cheb[k] > 1e-6) & usable)[0]
        if len(nb) < 5:
            continue
        src = obj[nb]
        if not _determines_a_homography(src):
            continue
        H, _ = cv2.findHomography(src, img[nb], 0)
        if H is None:
            continue
        probe = np.array([obj[k], obj[k] + (1.0, 0.0), obj[k] + (0.0, 1.0)]).reshape(-1, 1, 2)
        pred = cv2.perspectiveTransform(probe, H).reshape(-1, 2)
        square = 0.5 * (np.linalg.norm(pred[1] - pred[0]) + np.linalg.norm(pred[2] - pred[0]))
        if square > 1e-6:
            out[k] = np.linalg.norm(pred[0] - img[k]) / square
    return out


def _determines_a_homography(points: np.ndarray) -> bool:
    """True unless one line holds all the ``points`` (m, 2) but one: a homography needs 4 points with no 3 on a
    line. (Five corners along a partial view's edge and one beside them leave it free to turn about that edge,
    and then even exact corners look 0.2 square off their prediction.)"""
    m = len(points)
    for a in range(m - 1):
        d = points - points[a]
        cross = np.abs(d[:, None, 0] * d[None, :, 1] - d[:, None, 1] * d[None, :, 0])   # [b, c]: c on line a-b
        on_line = (cross < 1e-6).sum(1)
        on_line[a] = 0
        if on_line.max() >= m - 1:
            return False
    return True


def check_detection(detection: Detection, square_mm: float, min_corners: int, tolerance: float = 0.2,
                    max_bad_fraction: float = 0.25) -> tuple[Detection | None, str | None]:
    """(detection without inconsistent corners, None) or (None, reason) (module docstring).

    The worst corner is removed and the others re-checked without it, until all agree: one wrong
    corner does not condemn its neighbours.
    """
    err = corner_inconsistency(detection, square_mm)
    checked = np.isfinite(err)
    n_checked = int(checked.sum())
    limit = max(max_bad_fraction * n_checked, 1.0)   # inconsistent corners a trustworthy view may have
    bad = np.zeros(len(err), bool)
    while np.nanmax(np.where(bad, np.nan, err), initial=0.0) > tolerance:
        bad[int(np.nanargmax(np.where(bad, -np.inf, err)))] = True
        if bad.sum() > limit:
            break
        err = corner_inconsistency(detection, square_mm, excluded=bad)
    n_bad = int(bad.sum())
    if n_bad == 0:
        return detection, None
    if n_bad > limit:
        return None, (f"fails the geometric check ({n_bad} or more of its {n_checked} checked corners off "
                      f"their neighbours' grid by more than {tolerance:g} square)")
    keep = ~bad
    if int(keep.sum()) < min_corners:
        if n_bad == 1:      # the view stands or falls with one doubtful corner: the first solve's outlier test judges it
            return detection, None
        return None, f"too few corners after the geometric check ({int(keep.sum())} < {min_corners})"
    return Detection(detection.image_points[keep], detection.object_points[keep], detection.ids[keep]), None
