"""The hold-out check: leave views out, calibrate on the rest, predict the views left out.

Views are split into ``folds`` interleaved groups (view ``k`` in fold ``k % folds``; leave-one-out when
there are no more views than folds). For each fold the model is calibrated on the other views
(``cv2.calibrateCameraExtended``); each left-out view's pose is then found from its own corners with
that camera (``cv2.solvePnP``, IPPE then Levenberg-Marquardt) and its corners are reprojected. The
pooled RMS of those residuals is the hold-out error: it grows when the model is too rigid (it cannot
follow the lens) and when it is too flexible for the data (it follows noise that the left-out views do
not share); a left-out view that no camera can pose is left out of it (its own RMS is inf). The
fold cameras are kept: how far they project from the full-data camera over the image
is the model's spread under leaving views out (:func:`calib.uncertainty.projection_difference`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from calib.camera import Camera
from calib.models import DistortionModel


@dataclass(frozen=True)
class HoldoutResult:
    """Pooled hold-out RMS (px; ``inf`` when a fold could not be calibrated), per-view hold-out RMS
    (input order) and the fold cameras (one per fold, each calibrated without that fold's views)."""

    model: str
    rms_px: float
    view_rms_px: list[float]
    fold_cameras: list[Camera] = field(repr=False, default_factory=list)
    folds: int = 0
    spread_px: float = float("inf")  # max over the image of |fold camera - full camera| (px)


def fold_of(n_views: int, folds: int) -> np.ndarray:
    """Fold index of each view: interleaved, leave-one-out when ``n_views <= folds``."""
    k = min(max(2, folds), n_views)
    return np.arange(n_views) % k


def pnp_residuals(obj: np.ndarray, img: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """(n,) reprojection residuals (px) of one view after fitting its pose alone with camera (K, dist)."""
    import cv2

    obj64, img64 = obj.astype(np.float64), img.astype(np.float64)
    ok, rvec, tvec = cv2.solvePnP(obj64, img64, K, dist, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        return np.full(len(obj), np.inf)
    rvec, tvec = cv2.solvePnPRefineLM(obj64, img64, K, dist, rvec, tvec)
    proj, _ = cv2.projectPoints(obj64, rvec, tvec, K, dist)
    return np.linalg.norm(proj.reshape(-1, 2) - img64, axis=1)


def holdout_check(obj: list[np.ndarray], img: list[np.ndarray], image_size: tuple[int, int],
                  model: DistortionModel, options, full: Camera | None = None) -> HoldoutResult:
    """Run the check for one model (``options``: a :class:`calib.calibrate.CalibrationOptions`).

    With ``full`` (the model calibrated on all views) the spread over the image is measured too.
    """
    from calib.solve import solve
    from capture.io.errors import CaptureError

    fold = fold_of(len(obj), options.folds)
    view_rms = [float("inf")] * len(obj)
    cameras: list[Camera] = []
    sq, count = 0.0, 0
    for f in range(int(fold.max()) + 1):
        train = [i for i in range(len(obj)) if fold[i] != f]
        test = [i for i in range(len(obj)) if fold[i] == f]
        try:
            s = solve([obj[i] for i in train], [img[i] for i in train], image_size, model, options)
        except CaptureError:
            return HoldoutResult(model.name, float("inf"), view_rms, cameras, int(fold.max()) + 1)
        cameras.append(Camera(s.K, s.dist, image_size, s.rms))
        for i in test:
            r = pnp_residuals(obj[i], img[i], s.K, s.dist)
            view_rms[i] = float(np.sqrt(np.mean(r ** 2)))
            if np.all(np.isfinite(r)):  # a view no camera can pose (inf) stays out of the pooled error
                sq += float(np.sum(r ** 2))
                count += len(r)
    rms = float(np.sqrt(sq / count)) if count else float("inf")
    spread = float("inf")
    if full is not None and cameras:
        from calib.uncertainty import pixel_grid, projection_difference

        grid, _ = pixel_grid(image_size, float(np.hypot(*image_size)) / 60.0)
        spread = float(max(projection_difference(full, c, grid).max() for c in cameras))
    return HoldoutResult(model.name, rms, view_rms, cameras, int(fold.max()) + 1, spread)
