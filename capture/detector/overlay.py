"""Drawing a detector's result on its frame: the crop (rotated rectangle) and the landmarks.

Landmarks are dots coloured by confidence (red 0 -> yellow 0.5 -> green 1; white without a
confidence output); sub-pixel positions are drawn with OpenCV's fixed-point ``shift`` so a dot sits
where the landmark is (pixel centres at integers, as everywhere).
"""

from __future__ import annotations

import numpy as np

from capture.detector.crop import Crop, input_to_frame

SHIFT = 4   # fractional bits of cv2 drawing coordinates


def _fixed(p: np.ndarray) -> np.ndarray:
    return np.round(np.asarray(p, np.float64) * (1 << SHIFT)).astype(np.int32)


def confidence_colour(c: float | None) -> tuple[int, int, int]:
    """BGR colour of a confidence in 0..1 (None: white)."""
    if c is None or not np.isfinite(c):
        return (255, 255, 255)
    c = float(np.clip(c, 0.0, 1.0))
    return (0, int(round(255 * min(1.0, 2 * c))), int(round(255 * min(1.0, 2 * (1 - c)))))


def crop_corners(crop: Crop, input_size: tuple[int, int]) -> np.ndarray:
    """The crop's four outer corners (4, 2) in frame px."""
    w, h = input_size
    q = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [w - 0.5, h - 0.5], [-0.5, h - 0.5]])
    return input_to_frame(q, crop, input_size)


def draw_detection(frame: np.ndarray, points: np.ndarray, confidence: np.ndarray | None, crop: tuple,
                   input_size: tuple[int, int], face_found: bool, label: str = "") -> np.ndarray:
    """A copy of the BGR frame with the crop, the landmarks and ``label`` drawn on it."""
    import cv2

    img = frame.copy()
    h, w = img.shape[:2]
    radius = max(1, int(round(min(h, w) / 300)))
    if np.all(np.isfinite(crop)):
        pts = _fixed(crop_corners(Crop(*crop), input_size)).reshape(-1, 1, 2)
        cv2.polylines(img, [pts], True, (255, 160, 0), 1, cv2.LINE_AA, SHIFT)
    if face_found:
        for i, p in enumerate(np.asarray(points)):
            if np.all(np.isfinite(p)):
                col = confidence_colour(None if confidence is None else confidence[i])
                cv2.circle(img, tuple(int(v) for v in _fixed(p)), radius << SHIFT, col, -1, cv2.LINE_AA, SHIFT)
    text = label + ("" if face_found else "  no face")
    if text:
        cv2.putText(img, text, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 3, cv2.LINE_AA)
        cv2.putText(img, text, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
    return img
