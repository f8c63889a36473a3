"""The camera model: intrinsics, distortion and the image size they belong to.

Conventions (the project's, stated once here and in :mod:`calib.projection`):

- OpenCV pinhole camera: x right, y down, z forward; lengths in millimetres.
- ``K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` in pixels (no skew).
- ``dist`` holds OpenCV's coefficients ``(k1, k2, p1, p2[, k3[, k4, k5, k6[, s1..s4[, tx, ty]]]])``;
  an empty vector means no distortion.
- Pixel centres sit at integer coordinates (OpenCV's rule): the image spans ``[-0.5, w - 0.5]``
  horizontally, so the exact centre of a ``w x h`` image is ``((w - 1) / 2, (h - 1) / 2)``.
- ``image_size`` is ``(width, height)`` in pixels, the size the intrinsics are valid for.

:class:`Camera` is a frozen value: adjustments (:meth:`Camera.resized`, :meth:`Camera.cropped`,
:meth:`Camera.for_frame_size`) return new cameras. :func:`default_camera` is the documented guess
used when the user has no calibration; such a camera has ``is_default=True`` and every report that
uses it must say so. This module is pure math; files live in :mod:`calib.camera_io`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from capture.io.errors import CaptureError

#: Lengths of OpenCV distortion vectors (0 means "no distortion").
DIST_LENGTHS = (0, 4, 5, 8, 12, 14)

#: Horizontal field of view, in degrees, assumed by :func:`default_camera`. 60 degrees is a
#: mid-range lens on common sensors (about 31 mm full-frame equivalent, a typical phone main camera
#: or a head-mounted camera with a normal lens). It is a guess: calibrate for real work.
DEFAULT_FOV_DEG = 60.0


@dataclass(frozen=True, eq=False)
class Camera:
    """Intrinsics ``K`` (3, 3), distortion ``dist`` (D,) and ``image_size`` (width, height).

    ``rms`` is the calibration's RMS reprojection error in pixels (``None`` when unknown),
    ``provenance`` a one-line human-readable origin ("capture calibrate of take1.mp4 ...",
    "OpenCV file cam.yaml", "default guess ..."), and ``is_default`` flags a guessed camera.

    Example:
        >>> cam = default_camera(1920, 1080)
        >>> cam.is_default, round(cam.fx, 1)
        (True, 1662.8)
    """

    K: np.ndarray
    dist: np.ndarray
    image_size: tuple[int, int]
    rms: float | None = None
    provenance: str = ""
    is_default: bool = False
    std_dev: dict[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        K = np.array(self.K, dtype=np.float64)
        dist = np.array(self.dist, dtype=np.float64).reshape(-1)
        if K.shape != (3, 3):
            raise CaptureError(f"camera matrix K must be 3x3, got shape {K.shape}")
        if not np.all(np.isfinite(K)) or not np.all(np.isfinite(dist)):
            raise CaptureError("camera K or dist contains NaN or infinity; recalibrate the camera")
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise CaptureError(f"camera focal lengths must be positive, got fx={K[0, 0]}, fy={K[1, 1]}")
        if abs(K[0, 1]) > 1e-9 or np.any(np.abs(K[2] - (0.0, 0.0, 1.0)) > 1e-9) or abs(K[1, 0]) > 1e-9:
            raise CaptureError("camera matrix K must be [[fx,0,cx],[0,fy,cy],[0,0,1]] (no skew)")
        if dist.size not in DIST_LENGTHS:
            raise CaptureError(
                f"camera has {dist.size} distortion coefficients; OpenCV uses 0, 4, 5, 8, 12 or 14"
            )
        try:
            w, h = (int(v) for v in self.image_size)
        except (TypeError, ValueError):
            raise CaptureError(f"camera image_size must be [width, height], got {self.image_size!r}") from None
        if w <= 0 or h <= 0 or (w, h) != tuple(self.image_size):
            raise CaptureError(f"camera image_size must be two positive integers, got {self.image_size!r}")
        K.setflags(write=False)
        dist.setflags(write=False)
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "dist", dist)
        object.__setattr__(self, "image_size", (w, h))
        if self.rms is not None:
            object.__setattr__(self, "rms", float(self.rms))
        object.__setattr__(self, "std_dev", {str(k): float(v) for k, v in self.std_dev.items()})

    def __eq__(self, other: object) -> bool:
        """Exact equality of every field (arrays compared element-wise)."""
        if not isinstance(other, Camera):
            return NotImplemented
        return (np.array_equal(self.K, other.K) and np.array_equal(self.dist, other.dist)
                and self.image_size == other.image_size and self.rms == other.rms
                and self.provenance == other.provenance and self.is_default == other.is_default
                and self.std_dev == other.std_dev)

    __hash__ = None  # type: ignore[assignment]  # holds arrays

    # ----------------------------------------------------------------------------------- accessors
    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    @property
    def width(self) -> int:
        return self.image_size[0]

    @property
    def height(self) -> int:
        return self.image_size[1]

    def fov_deg(self) -> tuple[float, float]:
        """Horizontal and vertical field of view in degrees (pinhole, ignoring distortion)."""
        w, h = self.image_size
        return (
            math.degrees(2 * math.atan(w / (2 * self.fx))),
            math.degrees(2 * math.atan(h / (2 * self.fy))),
        )

    def describe(self) -> str:
        """One line for logs and reports; says loudly when the camera is a guess."""
        w, h = self.image_size
        text = f"{w}x{h} fx={self.fx:.1f} fy={self.fy:.1f} cx={self.cx:.1f} cy={self.cy:.1f}"
        if self.rms is not None:
            text += f" rms={self.rms:.3f}px"
        if self.is_default:
            text += " [DEFAULT GUESS, not calibrated]"
        return text

    # --------------------------------------------------------------------------------- adjustments
    def resized(self, width: int, height: int) -> "Camera":
        """The same camera for frames resized (whole frame, e.g. cv2.resize) to ``width x height``.

        With pixel centres at integer coordinates a pixel coordinate maps as
        ``u' = s (u + 0.5) - 0.5`` with ``s = width / self.width``; focal lengths scale by ``s``.
        Distortion coefficients act on normalised coordinates and do not change.
        """
        width, height = int(width), int(height)
        if width <= 0 or height <= 0:
            raise CaptureError(f"cannot resize a camera to {width}x{height}; sizes must be positive")
        sx = width / self.width
        sy = height / self.height
        K = self.K.copy()
        K[0, 0] *= sx
        K[1, 1] *= sy
        K[0, 2] = sx * (K[0, 2] + 0.5) - 0.5
        K[1, 2] = sy * (K[1, 2] + 0.5) - 0.5
        std = dict(self.std_dev)
        for key, s in (("fx", sx), ("fy", sy), ("cx", sx), ("cy", sy)):
            if key in std:
                std[key] *= s
        return Camera(
            K, self.dist, (width, height), None if self.rms is None else self.rms * math.sqrt(sx * sy),
            _append(self.provenance, f"resized {self.width}x{self.height}->{width}x{height}"),
            self.is_default, std,
        )

    def cropped(self, x: int, y: int, width: int, height: int) -> "Camera":
        """The same camera for the crop whose top-left pixel is ``(x, y)`` and size ``width x height``."""
        x, y, width, height = int(x), int(y), int(width), int(height)
        if x < 0 or y < 0 or width <= 0 or height <= 0 or x + width > self.width or y + height > self.height:
            raise CaptureError(
                f"crop {width}x{height}+{x}+{y} does not fit in the {self.width}x{self.height} frame"
            )
        K = self.K.copy()
        K[0, 2] -= x
        K[1, 2] -= y
        return Camera(
            K, self.dist, (width, height), self.rms,
            _append(self.provenance, f"cropped {width}x{height}+{x}+{y}"), self.is_default, self.std_dev,
        )

    def for_frame_size(self, width: int, height: int, tolerance: float = 0.01) -> "Camera":
        """This camera adjusted to frames of ``width x height`` (a proxy of the calibrated footage).

        Same size: returned unchanged. Same aspect ratio (within ``tolerance``): :meth:`resized`.
        A different aspect ratio cannot be guessed (it may be a crop or a squeeze): that is an error.
        """
        if (int(width), int(height)) == self.image_size:
            return self
        a_cam = self.width / self.height
        a_new = width / height
        if abs(a_new / a_cam - 1.0) > tolerance:
            raise CaptureError(
                f"camera was calibrated at {self.width}x{self.height} but frames are {width}x{height} "
                "with a different aspect ratio; crop the camera to match (Camera.cropped) or recalibrate"
            )
        return self.resized(width, height)

    def with_provenance(self, provenance: str) -> "Camera":
        return Camera(self.K, self.dist, self.image_size, self.rms, provenance, self.is_default, self.std_dev)


def _append(provenance: str, step: str) -> str:
    return f"{provenance}; {step}" if provenance else step


def default_camera(width: int, height: int, fov_deg: float = DEFAULT_FOV_DEG) -> Camera:
    """The documented guess when there is no calibration.

    Square pixels, principal point at the exact image centre ``((w-1)/2, (h-1)/2)``, no distortion,
    and ``fx = fy = (w / 2) / tan(fov_deg / 2)``, where ``fov_deg`` is the *horizontal* field of view
    (default :data:`DEFAULT_FOV_DEG`). The camera carries ``is_default=True``.
    """
    width, height = int(width), int(height)
    if width <= 0 or height <= 0:
        raise CaptureError(f"cannot make a default camera for a {width}x{height} frame")
    if not 1.0 <= fov_deg <= 170.0:
        raise CaptureError(f"default camera field of view must be in [1, 170] degrees, got {fov_deg}")
    f = (width / 2.0) / math.tan(math.radians(fov_deg) / 2.0)
    K = np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])
    return Camera(
        K, np.zeros(5), (width, height), None,
        f"default guess: {fov_deg:g} deg horizontal field of view, no distortion, from the "
        f"{width}x{height} frame size (run `capture calibrate` for a real camera)",
        True,
    )
