"""What footage shows when the board given with ``--board`` is found in none of its frames.

The usual causes on real footage are a spec that does not match the printed board: another ArUco
dictionary, a ChArUco board printed with OpenCV's legacy pattern (or without it), squares counted where a
checkerboard wants inner corners, a ChArUco board given as a checkerboard or the reverse. Each is checked
with OpenCV's own detectors on a few of the frames, and the first that finds something is named with the
spec that would read it. Pure detection, no I/O; only run once the calibration has already failed.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Sequence

import numpy as np

from calib.board import BoardSpec

#: ArUco families tried (each with its largest dictionary; the hint names the smallest that holds the ids seen).
ARUCO_FAMILIES = ("DICT_4X4", "DICT_5X5", "DICT_6X6", "DICT_7X7")
ARUCO_SIZES = (50, 100, 250, 1000)
#: Dictionaries without size variants.
ARUCO_SINGLE = ("DICT_ARUCO_ORIGINAL", "DICT_APRILTAG_36h11")
#: Markers (over the sampled frames) below which a family is not named: a stray detection is not a board.
MIN_MARKERS = 4


def _marker_ids(gray: np.ndarray, dictionary: str) -> list[int]:
    import cv2

    det = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary)))
    _corners, ids, _rejected = det.detectMarkers(gray)
    return [] if ids is None else [int(i) for i in ids.ravel()]


def _markers_by_dictionary(grays: Sequence[np.ndarray]) -> tuple[str, list[int]] | None:
    """The dictionary whose markers the frames show most (at least :data:`MIN_MARKERS`), and their ids."""
    counts: dict[str, list[int]] = {}
    for name in [f"{f}_1000" for f in ARUCO_FAMILIES] + list(ARUCO_SINGLE):
        counts[name] = [i for g in grays for i in _marker_ids(g, name)]
    name, ids = max(counts.items(), key=lambda kv: len(kv[1]))
    if len(ids) < MIN_MARKERS:
        return None
    if name.endswith("_1000"):   # the smallest dictionary of the family that holds every id seen
        family = name[:-5]
        name = next(f"{family}_{n}" for n in ARUCO_SIZES if max(ids) < n)
    return name, ids


def _chessboard(grays: Sequence[np.ndarray], cols: int, rows: int) -> bool:
    import cv2

    flags = cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_ACCURACY
    return any(cv2.findChessboardCornersSB(g, (cols, rows), flags=flags)[0] for g in grays)


def _charuco_found(grays: Sequence[np.ndarray], board: BoardSpec) -> bool:
    from calib.detect import BoardDetector

    det = BoardDetector(board)
    return any(det.detect(g)[0] is not None for g in grays)


def board_hint(grays: Sequence[np.ndarray], board: BoardSpec) -> str | None:
    """A phrase naming what the uint8 grayscale frames ``grays`` show instead of ``board`` and the ``--board``
    that would read it; None when nothing board-like is found (no markers, no chessboard)."""
    if board.kind == "charuco":
        ids = [i for g in grays for i in _marker_ids(g, board.dictionary)]
        n_markers = board.cols * board.rows // 2
        if len(ids) >= MIN_MARKERS:
            if max(ids) >= n_markers:
                return (f"markers of {board.dictionary} with ids up to {max(ids)} are in view, but a {board.cols}x"
                        f"{board.rows} ChArUco board has ids 0-{n_markers - 1}: check cols and rows (they count "
                        f"squares)")
            other = replace(board, legacy=not board.legacy)
            if _charuco_found(grays, other):
                pattern = "legacy" if other.legacy else "current"
                return f"the board is found as --board {other.text()} (OpenCV's {pattern} pattern)"
            return (f"{len(ids)} markers of {board.dictionary} are in view but no board corners: check cols, rows, "
                    f"square and marker")
        seen = _markers_by_dictionary(grays)
        if seen is not None:
            name, found = seen
            return (f"markers of {name} are in view ({len(found)}), none of {board.dictionary}: try "
                    f"--board {replace(board, dictionary=name).text()}")
        cols, rows = board.cols - 1, board.rows - 1      # a plain chessboard of the same squares
        if cols >= 2 and rows >= 2 and _chessboard(grays, cols, rows):
            return (f"a chessboard without markers is in view: try --board checker:cols={cols},rows={rows},"
                    f"square={board.square_mm:g}")
        return None
    seen = _markers_by_dictionary(grays)
    if seen is not None:
        name, found = seen
        return (f"ArUco markers of {name} are in view ({len(found)}): this is a ChArUco board; give it as "
                f"--board charuco:cols=...,rows=...,square={board.square_mm:g},marker=...,dict={name}")
    for cols, rows in ((board.cols - 1, board.rows - 1), (board.cols + 1, board.rows + 1)):
        if cols >= 2 and rows >= 2 and _chessboard(grays, cols, rows):
            return (f"a chessboard of {cols}x{rows} inner corners is in view: try --board checker:cols={cols},"
                    f"rows={rows},square={board.square_mm:g} (cols and rows count inner corners)")
    return None


def sample_evenly(items: list, k: int) -> list:
    """At most ``k`` of ``items``, spread evenly (first and last included)."""
    if len(items) <= k:
        return list(items)
    return [items[int(round(i * (len(items) - 1) / (k - 1)))] for i in range(k)]
