"""One OpenCV calibration solve for a lens model: the step that the model choice and the hold-out check repeat.

``cv2.calibrateCamera`` starts from a pinhole estimate that ignores distortion (``initIntrinsicParams2D``).
With a strong lens and views that reach the image's corners, that start is far off, and Levenberg-Marquardt can
settle in a wrong minimum: at 1920x1080 with k1 = -0.35, 5 of 8 such renders came out with fx 1,900-2,600
instead of 1,500, an RMS of 1.5-4 px instead of 0.2, and the model hundreds of px off (BENCHMARKS.md). So
:func:`solve` also calibrates in stages, each starting from the last (``CALIB_USE_INTRINSIC_GUESS``): k1 only,
then k1 and k2, then the model asked for. It keeps whichever of the two solutions fits the corners better: both
minimise the same reprojection error, so the lower one is the better solve of the same problem, and where
OpenCV's start was fine the two agree.
"""

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
    """The better of ``cv2.calibrateCameraExtended`` with the flags ``options.flags(model)`` (a
    :class:`calib.calibrate.CalibrationOptions`) from OpenCV's own start and from the staged start (module
    docstring); one-line CaptureError if OpenCV fails both ways."""
    import cv2

    size = tuple(image_size)
    flags = options.flags(model)
    K0 = np.eye(3)  # only read for CALIB_FIX_ASPECT_RATIO (ratio 1)
    found, failure = [], None
    try:
        found.append(cv2.calibrateCameraExtended(obj, img, size, K0, None, flags=flags))
    except cv2.error as exc:
        failure = exc
    try:
        found.append(_staged(obj, img, size, model, flags))
    except cv2.error as exc:
        failure = failure or exc
    if not found:
        detail = str(failure).strip().splitlines()[-1][-120:]
        raise CaptureError(
            f"OpenCV calibration failed ({detail}); record the board at more distances and tilts"
        ) from None
    rms, K, dist, rvecs, tvecs, std_int, _std_ext, per_view = min(found, key=lambda out: out[0])
    return Solve(float(rms), K, dist.reshape(-1)[: model.n_dist].copy(), [r.reshape(3) for r in rvecs],
                 [t.reshape(3) for t in tvecs], std_int.reshape(-1), per_view.reshape(-1))


#: Staged starts by view set (a digest of the corners, the image size and the constraints): every candidate model
#: and the first solve's rounds start from the same k1-k2 solve of the same views, so it is solved once.
_STARTS: dict[bytes, tuple[np.ndarray, np.ndarray]] = {}


def _staged(obj, img, size, model: DistortionModel, flags: int):
    """``calibrateCameraExtended`` for ``model`` started from k1 alone, then k1 and k2 (module docstring)."""
    import cv2

    keep = flags & (cv2.CALIB_FIX_PRINCIPAL_POINT | cv2.CALIB_FIX_ASPECT_RATIO)   # the caller's constraints
    K, dist = _k1_k2_start(obj, img, size, keep)
    if model.n_dist == 8:
        dist = np.concatenate([dist, np.zeros(3)])
    return cv2.calibrateCameraExtended(obj, img, size, K.copy(), dist.copy(),
                                       flags=flags | cv2.CALIB_USE_INTRINSIC_GUESS)


def _k1_k2_start(obj, img, size, keep: int) -> tuple[np.ndarray, np.ndarray]:
    """``(K, dist (5,))`` of k1 alone, then k1 and k2 from it, under the constraints ``keep``; cached in
    :data:`_STARTS` (a pure function of its inputs)."""
    import hashlib

    import cv2

    h = hashlib.blake2b(repr((tuple(size), keep, [len(o) for o in obj])).encode(), digest_size=16)
    for o, i in zip(obj, img):
        h.update(np.ascontiguousarray(o, np.float32).tobytes())
        h.update(np.ascontiguousarray(i, np.float32).tobytes())
    key = h.digest()
    if key not in _STARTS:
        simple = cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST
        K, dist = np.eye(3), np.zeros(5)
        for stage in (keep | simple | cv2.CALIB_FIX_K2, keep | simple):
            guess = cv2.CALIB_USE_INTRINSIC_GUESS if stage & cv2.CALIB_FIX_K2 == 0 else 0
            _rms, K, dist, _r, _t = cv2.calibrateCamera(obj, img, size, K.copy(), dist.copy(), flags=stage | guess)
            dist = dist.reshape(-1)[:5]
        if len(_STARTS) >= 256:   # a calibration uses a few dozen view sets
            _STARTS.clear()
        _STARTS[key] = (K, dist)
    K, dist = _STARTS[key]
    return K.copy(), dist.copy()
