"""One OpenCV calibration solve for a lens model: the step that the model choice and the hold-out check repeat."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calib.models import DistortionModel
from capture.io.errors import CaptureError


@dataclass(frozen=True)
class Solve:
    """One ``cv2.calibrateCameraExtended`` result; ``dist`` has the model's length (5 or 8)."""

    rms: float
    K: np.ndarray
    dist: np.ndarray
    rvecs: list[np.ndarray]
    tvecs: list[np.ndarray]
    std_int: np.ndarray
    per_view: np.ndarray


def solve(obj: list[np.ndarray], img: list[np.ndarray], image_size: tuple[int, int],
          model: DistortionModel, options) -> Solve:
    """``cv2.calibrateCameraExtended`` with the flags ``options.flags(model)`` (a
    :class:`calib.calibrate.CalibrationOptions`); one-line CaptureError if OpenCV fails."""
    import cv2

    K0 = np.eye(3)  # only read for CALIB_FIX_ASPECT_RATIO (ratio 1)
    try:
        out = cv2.calibrateCameraExtended(obj, img, tuple(image_size), K0, None, flags=options.flags(model))
    except cv2.error as exc:
        detail = str(exc).strip().splitlines()[-1][-120:]
        raise CaptureError(
            f"OpenCV calibration failed ({detail}); record the board at more distances and tilts"
        ) from None
    rms, K, dist, rvecs, tvecs, std_int, _std_ext, per_view = out
    return Solve(float(rms), K, dist.reshape(-1)[: model.n_dist].copy(), [r.reshape(3) for r in rvecs],
                 [t.reshape(3) for t in tvecs], std_int.reshape(-1), per_view.reshape(-1))
