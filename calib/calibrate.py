"""Intrinsics from board views: ``cv2.calibrateCameraExtended`` with outlier-view rejection.

Pure computation on corner lists (no files, no video). :func:`calibrate_views` calibrates, rejects
views whose RMS reprojection error is far above the others (more than ``outlier_factor`` times the
median per-view RMS and above ``outlier_floor_px``), recalibrates, and repeats up to
``max_rounds`` times while at least ``min_views`` remain. The result carries OpenCV's standard
deviations of the intrinsics, the per-view errors and poses, and what was rejected and why.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from calib.camera import Camera
from capture.io.errors import CaptureError

STD_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")


@dataclass(frozen=True)
class CalibrationOptions:
    """What OpenCV estimates and how outlier views are rejected."""

    fix_principal_point: bool = False  # keep (cx, cy) at the exact image centre ((w-1)/2, (h-1)/2)
    fix_aspect_ratio: bool = False  # fx = fy (square pixels)
    fix_k3: bool = False  # estimate (k1, k2, p1, p2) only; k3 = 0 (narrow lenses)
    zero_tangent: bool = False  # p1 = p2 = 0
    rational: bool = False  # also k4, k5, k6 (8 coefficients; wide lenses, many views)
    min_views: int = 6
    outlier_factor: float = 3.0  # 0 disables rejection
    outlier_floor_px: float = 0.3  # views below this RMS are never outliers
    max_rounds: int = 3

    def flags(self) -> int:
        import cv2

        flags = 0
        if self.fix_principal_point:
            flags |= cv2.CALIB_FIX_PRINCIPAL_POINT
        if self.fix_aspect_ratio:
            flags |= cv2.CALIB_FIX_ASPECT_RATIO
        if self.fix_k3:
            flags |= cv2.CALIB_FIX_K3
        if self.zero_tangent:
            flags |= cv2.CALIB_ZERO_TANGENT_DIST
        if self.rational:
            flags |= cv2.CALIB_RATIONAL_MODEL
        return flags


@dataclass(frozen=True)
class ViewError:
    label: str
    rms_px: float
    corners: int


@dataclass(frozen=True)
class CalibrationResult:
    camera: Camera
    rms_px: float
    views: list[ViewError]  # views used in the final calibration, in input order
    rejected: list[ViewError]  # outlier views, with the error they had when rejected
    std_dev: dict[str, float]  # 1-sigma of the estimated intrinsics (pixels / unitless)
    rvecs: list[np.ndarray] = field(repr=False, default_factory=list)
    tvecs: list[np.ndarray] = field(repr=False, default_factory=list)
    rounds: int = 1


def _calibrate_once(obj, img, image_size, options):
    import cv2

    K0 = np.eye(3)  # only read for CALIB_FIX_ASPECT_RATIO (ratio 1)
    try:
        out = cv2.calibrateCameraExtended(obj, img, tuple(image_size), K0, None, flags=options.flags())
    except cv2.error as exc:
        detail = str(exc).strip().splitlines()[-1][-120:]
        raise CaptureError(
            f"OpenCV calibration failed ({detail}); record the board at more distances and tilts"
        ) from None
    rms, K, dist, rvecs, tvecs, std_int, _std_ext, per_view = out
    return float(rms), K, dist.reshape(-1), rvecs, tvecs, std_int.reshape(-1), per_view.reshape(-1)


def calibrate_views(
    object_points: list[np.ndarray],
    image_points: list[np.ndarray],
    labels: list[str],
    image_size: tuple[int, int],
    options: CalibrationOptions = CalibrationOptions(),
    provenance: str = "",
) -> CalibrationResult:
    """Calibrate from per-view corners (object (n, 3) mm, image (n, 2) px), rejecting outlier views."""
    if not (len(object_points) == len(image_points) == len(labels)):
        raise ValueError("object_points, image_points and labels must have one entry per view")
    if len(labels) < options.min_views:
        raise CaptureError(
            f"too few usable views: found {len(labels)}, need at least {options.min_views}; "
            "record the board at more positions and tilts (or lower --min-views)"
        )
    obj = [np.ascontiguousarray(o, np.float32).reshape(-1, 3) for o in object_points]
    img = [np.ascontiguousarray(p, np.float32).reshape(-1, 2) for p in image_points]
    active = list(range(len(labels)))
    rejected: list[ViewError] = []
    rounds = 0
    while True:
        rounds += 1
        rms, K, dist, rvecs, tvecs, std_int, per_view = _calibrate_once(
            [obj[i] for i in active], [img[i] for i in active], image_size, options
        )
        if options.outlier_factor <= 0 or rounds > options.max_rounds:
            break
        limit = max(options.outlier_factor * float(np.median(per_view)), options.outlier_floor_px)
        bad = [k for k, e in enumerate(per_view) if e > limit]
        if not bad or len(active) - len(bad) < options.min_views:
            break
        for k in bad:
            i = active[k]
            rejected.append(ViewError(labels[i], float(per_view[k]), len(img[i])))
        bad_set = set(bad)
        active = [i for k, i in enumerate(active) if k not in bad_set]

    # OpenCV returns 14 coefficients for the rational model; keep the ones this model estimates
    n_dist = 8 if options.rational else 5
    dist = dist[:n_dist]
    std = {name: float(std_int[k]) for k, name in enumerate(STD_NAMES[: 4 + n_dist]) if k < len(std_int)}
    camera = Camera(K, dist, image_size, rms, provenance, False,
                    {k: std[k] for k in ("fx", "fy", "cx", "cy") if k in std})
    views = [ViewError(labels[i], float(per_view[k]), len(img[i])) for k, i in enumerate(active)]
    return CalibrationResult(camera, rms, views, rejected, std,
                             [r.reshape(3) for r in rvecs], [t.reshape(3) for t in tvecs], rounds)
