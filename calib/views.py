"""Choosing calibration views: drop only unusable views; over ``--max-views`` keep the most useful.

Everything here works on :class:`Candidate` records (a detection plus a few numbers measured on its
frame); no file or video access. A view is dropped only for a reason that makes it unusable on its
own, never for being worse than the other views:

1. **Geometry** (:mod:`calib.checks`, before a view becomes a candidate): corners that disagree with
   their neighbours are removed; a view with many such corners, or too few left, is dropped.
2. **Blur the corner detector cannot work with.** ``edge_width_px`` is the width of the board's
   black/white edges (contrast over the steepest gradient, in the worst direction, so motion blur
   counts; about 2 px for a sharp image, 2.5 sigma for a Gaussian blur of sigma px). Sub-pixel corner
   refinement stays unbiased under blur as long as the blurred edges of a square do not merge, so a
   view is *blurred* only when the edge width exceeds ``max_blur`` (0.4) times the board's square
   size in that view (``square_px``). This does not depend on the other views.
3. **Near-duplicates** are views that share at least half of their corners with a distinct view
   and whose corners moved on average less than ``duplicate_px`` (default 1 % of the image
   diagonal) (a board held still in a video gives many). They add little geometry but independent
   corner noise, so they are kept while the views fit under ``max_views``; only over the cap are
   they the first to go (the sharpest twin of each group is the distinct view).
4. **Over the cap.** When more than ``max_views`` distinct views remain, they are picked greedily,
   each time the one that adds the most new cells of a coverage grid, a new board-tilt bin (15
   degrees, from a rough PnP pose), distance to the chosen views in (position, size, tilt), and
   sharpness; the rest are listed as "over the cap". Free places under the cap are filled with
   near-duplicates, sharpest first; the others are listed as "near-duplicate of" their twin.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from calib.detect import Detection, one_square_pairs

TILT_BIN_DEG = 15.0
GRID_COLS = 8  # coverage grid used for choosing views; rows follow the aspect ratio
COVERAGE_COLS = 16  # finer grid for the reported coverage figure
MAX_BLUR = 0.4  # edge width / square size above which a view is too blurred for corner refinement


@dataclass(frozen=True)
class Candidate:
    """One frame where the board was found, with the numbers view selection needs."""

    label: str  # "frame 120" or the image file name
    frame: int  # frame number in the video, or index of the image in the sorted folder
    detection: Detection
    edge_width_px: float  # blur: width of the board's edges (module docstring)
    square_px: float  # the board's square side in this view (median over neighbouring corners)
    centre: tuple[float, float]  # mean corner position / image size, in [0, 1]
    area: float  # bounding-box area of the corners / image area
    tilt_deg: tuple[float, float]  # board normal's angle about the camera x and y axes
    cells: frozenset[int] = field(default_factory=frozenset)

    @property
    def blur(self) -> float:
        """Edge width over square size: 0.05-0.1 for a sharp view, above :data:`MAX_BLUR` unusable."""
        return self.edge_width_px / max(self.square_px, 1e-6)

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


def measure_edge_width(gray: np.ndarray, points: np.ndarray) -> float:
    """Width (px) of the board's edges over the corners' bounding box (module docstring, rule 2).

    Contrast is the 2nd-98th percentile intensity range; the steepest gradient is the 99.5th
    percentile of the directional derivative along 0, 45, 90 and 135 degrees, and the widest of
    the four directions counts (motion blur widens the edges across the motion only).
    """
    import cv2

    h, w = gray.shape
    pad = 8
    x0, y0 = np.floor(points.min(0)).astype(int) - pad
    x1, y1 = np.ceil(points.max(0)).astype(int) + pad + 1
    roi = gray[max(y0, 0):min(y1, h), max(x0, 0):min(x1, w)].astype(np.float32)
    if roi.shape[0] < 5 or roi.shape[1] < 5:
        return float("inf")
    lo, hi = np.percentile(roi, [2, 98])
    contrast = float(hi - lo)
    if contrast < 1.0:
        return float("inf")
    gx = cv2.Sobel(roi, cv2.CV_32F, 1, 0) / 8.0  # per-pixel intensity step
    gy = cv2.Sobel(roi, cv2.CV_32F, 0, 1) / 8.0
    widths = []
    for ang in (0.0, 45.0, 90.0, 135.0):
        c, s = math.cos(math.radians(ang)), math.sin(math.radians(ang))
        steep = float(np.percentile(np.abs(c * gx + s * gy), 99.5))
        widths.append(contrast / steep if steep > 1e-6 else float("inf"))
    return max(widths)


def measure_square_px(detection: Detection, square_mm: float) -> float:
    """Median image distance between corners one square apart on the board (px)."""
    img = detection.image_points.astype(np.float64)
    i, j = one_square_pairs(detection.object_points, square_mm)
    if len(i) == 0:
        return float("nan")
    return float(np.median(np.linalg.norm(img[i] - img[j], axis=1)))


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


def make_candidate(label: str, frame: int, gray: np.ndarray, detection: Detection, square_mm: float) -> Candidate:
    h, w = gray.shape
    pts = detection.image_points
    span = pts.max(0) - pts.min(0)
    return Candidate(
        label, frame, detection, measure_edge_width(gray, pts), measure_square_px(detection, square_mm),
        (float(pts[:, 0].mean() / w), float(pts[:, 1].mean() / h)),
        float(span[0] * span[1] / (w * h)), rough_tilt(detection, (w, h)), cells_of(pts, (w, h)),
    )


def _motion(a: Candidate, b: Candidate) -> float:
    """Mean motion (px) of the corners two views share, or inf if they share fewer than half."""
    common, ia, ib = np.intersect1d(a.detection.ids, b.detection.ids, return_indices=True)
    if len(common) < 0.5 * min(len(a.detection.ids), len(b.detection.ids)):
        return float("inf")
    return float(np.linalg.norm(a.detection.image_points[ia] - b.detection.image_points[ib], axis=1).mean())


def select_views(
    candidates: list[Candidate],
    image_size: tuple[int, int],
    max_views: int = 60,
    max_blur: float = MAX_BLUR,
    duplicate_px: float | None = None,
) -> tuple[list[Candidate], list[Dropped]]:
    """Apply rules 2-4 of the module docstring; returns (chosen in frame order, dropped with reasons).

    ``max_blur=0`` keeps views however blurred (the detector already found the board in them).
    """
    if duplicate_px is None:
        duplicate_px = 0.01 * math.hypot(*image_size)
    dropped: list[Dropped] = []
    if not candidates:
        return [], dropped

    # 2. blur relative to the board's own squares
    pool = []
    for c in candidates:
        too_soft = not np.isfinite(c.edge_width_px) or (np.isfinite(c.square_px) and c.blur > max_blur)
        if max_blur > 0 and too_soft:
            dropped.append(Dropped(c.label, c.frame, f"blurred (edges {c.edge_width_px:.1f} px wide, "
                                                     f"{c.blur:.2f} of a {c.square_px:.0f} px square > {max_blur:g})"))
        else:
            pool.append(c)

    # 3. near-duplicates of distinct views (sharpest first)
    distinct: list[Candidate] = []
    twins: list[tuple[Candidate, Candidate]] = []
    for c in sorted(pool, key=lambda c: c.blur):
        twin = next((k for k in distinct if _motion(c, k) < duplicate_px), None)
        if twin is None:
            distinct.append(c)
        else:
            twins.append((c, twin))

    # 4. the cap: distinct views first (greedy when too many), then near-duplicates
    if len(distinct) <= max_views:
        chosen, remaining = list(distinct), []
    else:
        chosen, remaining = _greedy(distinct, image_size, max_views)
    room = max_views - len(chosen)
    chosen += [c for c, _ in twins[:room]]
    for c, twin in twins[room:]:
        dropped.append(Dropped(c.label, c.frame, f"near-duplicate of {twin.label}"))
    for c in remaining:
        dropped.append(Dropped(c.label, c.frame, f"over the cap of {max_views} views (adds least coverage/tilt)"))
    chosen = sorted(chosen, key=lambda c: c.frame)
    dropped.sort(key=lambda d: d.frame)
    return chosen, dropped


def _greedy(kept: list[Candidate], image_size: tuple[int, int], max_views: int):
    gx, gy = grid_shape(image_size)
    total_cells = gx * gy
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
            sharp = 1.0 - min(1.0, c.blur / MAX_BLUR)  # 1 sharp ... 0 at the blur limit
            return 2.0 * new_cells + 0.5 * new_tilt + spread + 0.3 * sharp

        best = max(remaining, key=score)
        remaining.remove(best)
        chosen.append(best)
        covered |= best.cells
        tilt_bins.add(tilt_bin(best))
    return chosen, remaining
