"""Board detection in one image, through OpenCV (ChArUco detector or chessboard finder).

No corner detection of our own: ChArUco corners come from ``cv2.aruco.CharucoDetector.detectBoard``
(markers, then chessboard corners interpolated and refined to sub-pixel), checkerboard corners from
``cv2.findChessboardCornersSB`` (the sector-based finder, more accurate than the classic one).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calib.board import BoardSpec


@dataclass(frozen=True)
class Detection:
    """Corners of the board found in one image.

    ``image_points`` (n, 2) float32 pixels, ``object_points`` (n, 3) float32 board mm (z = 0),
    ``ids`` (n,) corner ids (row-major over the inner corners, see :class:`~calib.board.BoardSpec`).
    """

    image_points: np.ndarray
    object_points: np.ndarray
    ids: np.ndarray


class BoardDetector:
    """Finds a :class:`~calib.board.BoardSpec` board in grayscale images.

    ``detect(gray)`` returns ``(detection, None)`` or ``(None, reason)`` where reason is a short
    phrase for the report ("no board detected", "too few corners (4 < 6)", "corners collinear").
    """

    def __init__(self, board: BoardSpec, min_corners: int = 6):
        import cv2

        self.board = board
        self.min_corners = max(4, int(min_corners))
        self._object_points = board.corner_object_points()
        if board.kind == "charuco":
            dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, board.dictionary))
            self._cv_board = cv2.aruco.CharucoBoard(
                (board.cols, board.rows), float(board.square_mm), float(board.marker_mm), dictionary
            )
            self._cv_board.setLegacyPattern(bool(board.legacy))
            self._detector = cv2.aruco.CharucoDetector(self._cv_board)
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
        if self._cv_board.checkCharucoCornersCollinear(ids.reshape(-1, 1)):
            return None, "corners collinear"
        image_points = corners.reshape(-1, 2).astype(np.float32)
        return Detection(image_points, self._object_points[ids], ids), None

    def _detect_checker(self, gray: np.ndarray) -> tuple[Detection | None, str | None]:
        import cv2

        pattern = (self.board.cols, self.board.rows)
        flags = cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_ACCURACY
        found, corners = cv2.findChessboardCornersSB(gray, pattern, flags=flags)
        if not found or corners is None:
            return None, "no board detected"
        image_points = corners.reshape(-1, 2).astype(np.float32)
        ids = np.arange(len(image_points), dtype=np.int32)
        return Detection(image_points, self._object_points, ids), None
