"""Board detection in one image: OpenCV finds the board, :mod:`calib.subpix` places its corners.

ChArUco corners come from ``cv2.aruco.CharucoDetector.detectBoard`` (markers, with the missed ones recovered from the
board's layout, then chessboard corners interpolated and refined to sub-pixel), checkerboard corners from
``cv2.findChessboardCornersSB`` (the sector-based finder). Each corner is then moved to the saddle point of the
image intensity around it, which on blurred or strongly distorted views is several times more accurate than
OpenCV's sub-pixel step (``BENCHMARKS.md``, Calibration).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calib.board import BoardSpec
from calib.subpix import refine_saddle, window_half, window_inside


@dataclass(frozen=True)
class Detection:
    """Corners of the board found in one image.

    ``image_points`` (n, 2) float32 pixels, ``object_points`` (n, 3) float32 board mm (z = 0),
    ``ids`` (n,) corner ids (row-major over the inner corners, see :class:`~calib.board.BoardSpec`).
    """

    image_points: np.ndarray
    object_points: np.ndarray
    ids: np.ndarray


def one_square_pairs(object_points: np.ndarray, square_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs ``(i, j)`` (both orders) of corners one square apart on the board, from their board coordinates
    ``object_points`` (n, 2 or 3) mm."""
    obj = np.asarray(object_points, np.float64)[:, :2]
    d = np.linalg.norm(obj[:, None] - obj[None], axis=2)
    return np.nonzero(np.abs(d - square_mm) < 1e-3 * square_mm)


class BoardDetector:
    """Finds a :class:`~calib.board.BoardSpec` board in grayscale images.

    ``detect(gray)`` returns ``(detection, None)`` or ``(None, reason)`` where reason is a short
    phrase for the report ("no board detected", "too few corners (4 < 6)", "corners collinear").

    ``refine_markers``: ChArUco markers the first pass missed are looked for where the board's layout puts them
    (OpenCV's ``CharucoParameters.tryRefineMarkers``); on blurred footage that finds the markers near the image's
    edges. ``saddle``: every corner is then moved to the saddle point of the image intensity
    (:mod:`calib.subpix`), 3-5x closer to the truth than OpenCV's sub-pixel step on our renders, and corners with no
    clear saddle are left out. Both on by default; off, the corners are OpenCV's own (what plain OpenCV calibrates
    from, for comparisons).
    """

    def __init__(self, board: BoardSpec, min_corners: int = 6, saddle: bool = True, refine_markers: bool = True):
        import cv2

        self.saddle = bool(saddle)
        self.board = board
        self.min_corners = max(4, int(min_corners))
        self._object_points = board.corner_object_points()
        if board.kind == "charuco":
            dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, board.dictionary))
            self._cv_board = cv2.aruco.CharucoBoard(
                (board.cols, board.rows), float(board.square_mm), float(board.marker_mm), dictionary
            )
            self._cv_board.setLegacyPattern(bool(board.legacy))
            charuco = cv2.aruco.CharucoParameters()
            charuco.tryRefineMarkers = bool(refine_markers)
            self._detector = cv2.aruco.CharucoDetector(self._cv_board, charuco)
        else:
            self._cv_board = None
            self._detector = None

    @property
    def cv_board(self):
        """The ``cv2.aruco.CharucoBoard`` (ChArUco only), e.g. to render or print the board."""
        return self._cv_board

    def detect(self, gray: np.ndarray) -> tuple[Detection | None, str | None]:
        if gray.ndim != 2 or gray.dtype != np.uint8:
            raise ValueError(f"detect expects a uint8 grayscale image, got {gray.dtype} {gray.shape}")
        if self.board.kind == "charuco":
            return self._detect_charuco(gray)
        return self._detect_checker(gray)

    def _detect_charuco(self, gray: np.ndarray) -> tuple[Detection | None, str | None]:
        corners, ids, _marker_corners, _marker_ids = self._detector.detectBoard(gray)
        if corners is None or ids is None or len(ids) == 0:
            return None, "no board detected"
        ids = ids.reshape(-1).astype(np.int32)
        if len(ids) < self.min_corners:
            return None, f"too few corners ({len(ids)} < {self.min_corners})"
        detection, reason = self._finish(gray, corners.reshape(-1, 2), ids)
        if detection is not None and self._cv_board.checkCharucoCornersCollinear(detection.ids.reshape(-1, 1)):
            return None, "corners collinear"
        return detection, reason

    def _finish(self, gray: np.ndarray, points: np.ndarray, ids: np.ndarray) -> tuple[Detection | None, str | None]:
        """The detection, with the corners moved to the saddle of the intensity (:mod:`calib.subpix`) when
        ``saddle``. A corner whose window lies in the image but holds no clear saddle is no corner the fit can vouch
        for, and is left out; corners within a window of the image's edge keep OpenCV's position."""
        points = points.astype(np.float64)
        if self.saddle:
            half = window_half(self._square_px(ids, points))
            refined, found = refine_saddle(gray, points, half)
            keep = found | ~window_inside(points, half, gray.shape)
            points, ids = refined[keep], ids[keep]
            if len(ids) < self.min_corners:
                return None, f"too few corners ({len(ids)} < {self.min_corners}) with a clear saddle"
        return Detection(points.astype(np.float32), self._object_points[ids], ids), None

    def _square_px(self, ids: np.ndarray, points: np.ndarray) -> np.ndarray:
        """(n,) side of the squares at each corner in the image: the distance to its nearest detected neighbour one
        square away on the board (the median of the view's where it has none)."""
        i, j = one_square_pairs(self._object_points[ids], self.board.square_mm)
        side = np.full(len(ids), np.inf)
        np.minimum.at(side, i, np.linalg.norm(points[i] - points[j], axis=1))
        known = np.isfinite(side)
        return np.where(known, side, np.median(side[known]) if known.any() else 0.0)

    def _detect_checker(self, gray: np.ndarray) -> tuple[Detection | None, str | None]:
        import cv2

        pattern = (self.board.cols, self.board.rows)
        flags = cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_ACCURACY
        found, corners = cv2.findChessboardCornersSB(gray, pattern, flags=flags)
        if not found or corners is None:
            return None, "no board detected"
        points = corners.reshape(-1, 2)
        return self._finish(gray, points, np.arange(len(points), dtype=np.int32))
