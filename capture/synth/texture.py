"""The position colour code: each template point is painted with an RGB colour linear in its position.

``rgb = lo_level + (c - box_min) / (box_max - box_min) * (hi_level - lo_level)`` per axis, for a
template point ``c`` (mm, template frame): red follows x (the actor's left), green y (up), blue z
(forward). The box is the template's bounding box; the levels avoid the black background
(:data:`BACKGROUND`) by at least ``lo_level`` in every channel. Because the code is linear in the
template position, barycentric interpolation on a triangle gives exactly the code of the surface
point, and a landmark given as (triangle, barycentric) has a known colour: the synthetic detector
(:mod:`capture.synth.detector_onnx`) finds it by looking for that colour in the pixels.

Example:
    >>> code = PositionCode(np.zeros(3), np.ones(3) * 100.0)
    >>> code.encode(np.array([[50.0, 0.0, 100.0]])).round(1).tolist()
    [[136.0, 32.0, 240.0]]
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Background colour (RGB, 0..255): black, far from every code colour.
BACKGROUND = (0.0, 0.0, 0.0)

#: The 4x4 Bayer matrix of ordered dithering (thresholds ``(B + 0.5) / 16``).
BAYER4 = np.array([[0, 8, 2, 10], [12, 4, 14, 6], [3, 11, 1, 9], [15, 7, 13, 5]])


def dither_to_uint8(image: np.ndarray) -> np.ndarray:
    """Ordered (4x4 Bayer) dithering of a float image ``(H, W, C)`` (levels 0..255) to uint8.

    Each level is rounded up or down so that every 4x4 block averages to the float value within
    1/32 level. The code of a face spans only a few levels per mm, so rounding alone (``rint``) leaves
    bands several pixels wide that a local colour fit cannot see through; with the dither the
    sub-level part survives in the local mean (the synthetic detector fits windows of about 13 x 13
    frame pixels). Lossless video keeps it exactly.

    Example:
        >>> float(dither_to_uint8(np.full((4, 4, 1), 10.25)).mean())
        10.25
    """
    img = np.asarray(image, dtype=np.float64)
    h, w = img.shape[:2]
    th = (BAYER4[np.arange(h)[:, None] % 4, np.arange(w)[None, :] % 4] + 0.5) / 16.0
    return np.clip(np.floor(img + th.reshape(h, w, *([1] * (img.ndim - 2)))), 0, 255).astype(np.uint8)


@dataclass(frozen=True)
class PositionCode:
    """Linear map from template positions (mm) to RGB levels (0..255, float)."""

    box_min: np.ndarray     # (3,) mm
    box_max: np.ndarray     # (3,) mm
    lo_level: float = 32.0
    hi_level: float = 240.0

    @classmethod
    def for_template(cls, vertices: np.ndarray, pad_mm: float = 1.0) -> "PositionCode":
        """The code spanning the bounding box of template ``vertices (V, 3)`` (padded by ``pad_mm``)."""
        v = np.asarray(vertices, dtype=np.float64)
        return cls(v.min(0) - pad_mm, v.max(0) + pad_mm)

    @property
    def levels_per_mm(self) -> np.ndarray:
        """(3,) colour levels per mm along x, y, z."""
        return (self.hi_level - self.lo_level) / (np.asarray(self.box_max) - np.asarray(self.box_min))

    def encode(self, points: np.ndarray) -> np.ndarray:
        """Colours ``(*, 3)`` float64 RGB levels of template points ``(*, 3)`` mm."""
        p = np.asarray(points, dtype=np.float64)
        return self.lo_level + (p - np.asarray(self.box_min)) * self.levels_per_mm

    def decode(self, rgb: np.ndarray) -> np.ndarray:
        """Template points ``(*, 3)`` mm of colours ``(*, 3)`` (the inverse of :meth:`encode`)."""
        c = np.asarray(rgb, dtype=np.float64)
        return np.asarray(self.box_min) + (c - self.lo_level) / self.levels_per_mm

    def to_dict(self) -> dict:
        return {"box_min_mm": [float(x) for x in self.box_min], "box_max_mm": [float(x) for x in self.box_max],
                "lo_level": self.lo_level, "hi_level": self.hi_level,
                "channels": "R = x (actor's left), G = y (up), B = z (forward) of the template point"}
