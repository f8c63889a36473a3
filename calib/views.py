"""Choosing calibration views: drop blurred frames and near-duplicates, prefer coverage and tilts, cap.

Everything here works on :class:`Candidate` records (a detection plus a few numbers measured on
its frame); no file or video access. The rules, in order:

1. **Blur.** ``sharpness`` is the variance of the Laplacian over the board's bounding box divided
   by the mean squared gradient there (units 1/px^2, roughly 1 / edge width^2). The division makes
   it independent of the board's size in the image and of its contrast, so one relative threshold
   works for near and far boards: a view is *blurred* when its sharpness is below
   ``blur_threshold`` times the 90th percentile of all detected views.
2. **Near-duplicates.** Two views are near-duplicates when they share at least half of their
   corners and those corners moved on average less than ``duplicate_px`` pixels; the sharper view
   is kept (a board held still in a video gives many such frames).
3. **Coverage and tilt, capped.** Views are picked greedily, each time the one that adds the most:
   new cells of a coverage grid over the image, a new board-tilt bin (15 degrees wide, tilts from a
   rough PnP pose), distance to the already chosen views in (position, size, tilt), and a little
   sharpness. Picking stops at ``max_views``; the rest are dropped as adding the least.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from calib.detect import Detection

TILT_BIN_DEG = 15.0
GRID_COLS = 8  # coverage grid used for choosing views; rows follow the aspect ratio
COVERAGE_COLS = 16  # finer grid for the reported coverage figure


@dataclass(frozen=True)
class Candidate:
    """One frame where the board was found, with the numbers view selection needs."""

    label: str  # "frame 120" or the image file name
    frame: int  # frame number in the video, or index of the image in the sorted folder
    detection: Detection
    sharpness: float
    centre: tuple[float, float]  # mean corner position / image size, in [0, 1]
    area: float  # bounding-box area of the corners / image area
    tilt_deg: tuple[float, float]  # board normal's angle about the camera x and y axes
    cells: frozenset[int] = field(default_factory=frozenset)

    @property
    def features(self) -> np.ndarray:
        return np.array([self.centre[0], self.centre[1], math.log(max(self.area, 1e-4)) / 3.0,
                         self.tilt_deg[0] / 45.0, self.tilt_deg[1] / 45.0])


@dataclass(frozen=True)
class Dropped:
    label: str
    frame: int
    reason: str


def grid_shape(image_size: tuple[int, int], cols: int = GRID_COLS) -> tuple[int, int]:
    w, h = image_size
    return cols, max(1, round(cols * h / w))


def cells_of(points: np.ndarray, image_size: tuple[int, int], cols: int = GRID_COLS) -> frozenset[int]:
    """Indices of the coverage-grid cells that contain at least one of ``points`` (n, 2)."""
    w, h = image_size
    gx, gy = grid_shape(image_size, cols)
    ix = np.clip(((points[:, 0] + 0.5) / w * gx).astype(int), 0, gx - 1)
    iy = np.clip(((points[:, 1] + 0.5) / h * gy).astype(int), 0, gy - 1)
    return frozenset((iy * gx + ix).tolist())


def coverage_fraction(points: list[np.ndarray], image_size: tuple[int, int], cols: int = COVERAGE_COLS) -> float:
    """Fraction of a ``cols``-wide grid over the image holding at least one corner of ``points``."""
    if not points:
        return 0.0
    gx, gy = grid_shape(image_size, cols)
    return len(cells_of(np.concatenate(points), image_size, cols)) / (gx * gy)


def measure_sharpness(gray: np.ndarray, points: np.ndarray) -> float:
    """Normalised variance of the Laplacian over the corners' bounding box (see module docstring)."""
    import cv2

    h, w = gray.shape
    pad = 8
    x0, y0 = np.floor(points.min(0)).astype(int) - pad
    x1, y1 = np.ceil(points.max(0)).astype(int) + pad + 1
    roi = gray[max(y0, 0):min(y1, h), max(x0, 0):min(x1, w)].astype(np.float32)
    if roi.shape[0] < 3 or roi.shape[1] < 3:
        return 0.0
    lap = cv2.Laplacian(roi, cv2.CV_32F)
    gx = cv2.Sobel(roi, cv2.CV_32F, 1, 0) / 8.0
    gy = cv2.Sobel(roi, cv2.CV_32F, 0, 1) / 8.0
    grad = float(np.mean(gx * gx + gy * gy))
    return float(lap.var()) / grad if grad > 1e-6 else 0.0


def rough_tilt(detection: Detection, image_size: tuple[int, int]) -> tuple[float, float]:
    """Board tilt (degrees about camera x and y) from a PnP pose with a rough camera (f = max(w, h))."""
    import cv2

    w, h = image_size
    f = float(max(w, h))
    K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1]])
    ok, rvec, _t = cv2.solvePnP(detection.object_points.astype(np.float64),
                                detection.image_points.astype(np.float64), K, None, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        return 0.0, 0.0
    n = cv2.Rodrigues(rvec)[0][:, 2]
    if n[2] < 0:
        n = -n
    return math.degrees(math.atan2(n[1], n[2])), math.degrees(math.atan2(n[0], n[2]))


def make_candidate(label: str, frame: int, gray: np.ndarray, detection: Detection) -> Candidate:
    h, w = gray.shape
    pts = detection.image_points
    span = pts.max(0) - pts.min(0)
    return Candidate(
        label, frame, detection, measure_sharpness(gray, pts),
        (float(pts[:, 0].mean() / w), float(pts[:, 1].mean() / h)),
        float(span[0] * span[1] / (w * h)), rough_tilt(detection, (w, h)), cells_of(pts, (w, h)),
    )


def _is_duplicate(a: Candidate, b: Candidate, duplicate_px: float) -> bool:
    common, ia, ib = np.intersect1d(a.detection.ids, b.detection.ids, return_indices=True)
    if len(common) < 0.5 * min(len(a.detection.ids), len(b.detection.ids)):
        return False
    moved = np.linalg.norm(a.detection.image_points[ia] - b.detection.image_points[ib], axis=1).mean()
    return bool(moved < duplicate_px)


def select_views(
    candidates: list[Candidate],
    image_size: tuple[int, int],
    max_views: int = 40,
    blur_threshold: float = 0.6,
    duplicate_px: float | None = None,
) -> tuple[list[Candidate], list[Dropped]]:
    """Apply the rules of the module docstring; returns (chosen in frame order, dropped with reasons).

    ``duplicate_px`` defaults to 1 % of the image diagonal. ``blur_threshold=0`` keeps all views.
    """
    if duplicate_px is None:
        duplicate_px = 0.01 * math.hypot(*image_size)
    dropped: list[Dropped] = []
    if not candidates:
        return [], dropped

    # 1. blur
    ref = float(np.percentile([c.sharpness for c in candidates], 90))
    limit = blur_threshold * ref
    pool = []
    for c in candidates:
        if c.sharpness < limit:
            dropped.append(Dropped(c.label, c.frame, f"blurred (sharpness {c.sharpness:.2f} < {limit:.2f})"))
        else:
            pool.append(c)

    # 2. near-duplicates, sharpest first
    kept: list[Candidate] = []
    for c in sorted(pool, key=lambda c: -c.sharpness):
        twin = next((k for k in kept if _is_duplicate(c, k, duplicate_px)), None)
        if twin is None:
            kept.append(c)
        else:
            dropped.append(Dropped(c.label, c.frame, f"near-duplicate of {twin.label}"))

    # 3. greedy coverage / tilt / diversity, capped
    gx, gy = grid_shape(image_size)
    total_cells = gx * gy
    best_sharp = max(c.sharpness for c in kept)
    chosen: list[Candidate] = []
    covered: set[int] = set()
    tilt_bins: set[tuple[int, int]] = set()
    remaining = list(kept)
    feats = {id(c): c.features for c in kept}

    def tilt_bin(c: Candidate) -> tuple[int, int]:
        return round(c.tilt_deg[0] / TILT_BIN_DEG), round(c.tilt_deg[1] / TILT_BIN_DEG)

    while remaining and len(chosen) < max_views:
        def score(c: Candidate) -> float:
            new_cells = len(c.cells - covered) / total_cells
            new_tilt = 0.0 if tilt_bin(c) in tilt_bins else 1.0
            spread = (min(float(np.linalg.norm(feats[id(c)] - feats[id(s)])) for s in chosen)
                      if chosen else 1.0)
            return 2.0 * new_cells + 0.5 * new_tilt + spread + 0.1 * c.sharpness / best_sharp

        best = max(remaining, key=score)
        remaining.remove(best)
        chosen.append(best)
        covered |= best.cells
        tilt_bins.add(tilt_bin(best))
    for c in remaining:
        dropped.append(Dropped(c.label, c.frame, f"over the cap of {max_views} views (adds least coverage/tilt)"))
    chosen.sort(key=lambda c: c.frame)
    dropped.sort(key=lambda d: d.frame)
    return chosen, dropped
